"""Paper-ready output: `table --latex` (booktabs, intervals, best per column bold, LaTeX's special
characters escaped), `--format pdf|svg` for the plots, `table --no-paper`. Read from the
committed sample runs (results/sample/): nothing is matched."""

from __future__ import annotations

import re
import shutil
import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path

import pandas as pd
import pytest

from e3cm_bench.reporting.latex import escape, table_to_latex
from e3cm_bench.reporting.tables import load_run, paper_reference, paper_table
from helpers import invoke

REPO = Path(__file__).resolve().parents[2]
SAMPLE = REPO / "results" / "sample" / "table1_hpatches"
RUNS = [SAMPLE / name for name in ("sift", "e3cm_efficientnet_lite0", "dfm_efficientnet_lite0")]


def rows_of(tex: str) -> list[list[str]]:
    """The body rows of a tabular (between the rules), as cells."""
    body = [line for line in tex.splitlines() if line.endswith(r"\\")]
    return [[cell.strip() for cell in line[:-2].split(" & ")] for line in body]


def test_escape_prints_every_special_character_as_itself():
    assert escape(r"a&b%c$d#e_f{g}h~i^j\k") == (r"a\&b\%c\$d\#e\_f\{g\}h\textasciitilde{}i"
                                                r"\textasciicircum{}j\textbackslash{}k")


def test_latex_table_has_booktabs_rules_intervals_and_the_best_in_bold():
    runs = [load_run(d) for d in RUNS]
    table = paper_table(runs, "hpatches", paper_reference(runs[0].benchmark))
    table.loc[table["source"] == "measured", "method"] = ["sift_100%", "e3cm & co", "dfm #1"]
    tex = table_to_latex(table)
    lines = tex.splitlines()
    assert [line for line in lines if line.startswith(("\\toprule", "\\midrule", "\\bottomrule"))] == [
        r"\toprule", r"\midrule", r"\midrule", r"\bottomrule"]  # header, paper rows, measured rows
    rows = rows_of(tex)
    header, body = rows[0], rows[1:]
    assert header == ["method", r"h\_acc@1", r"h\_acc@3", r"h\_acc@5", r"n\_pairs", "mma@3"]
    assert len(body) == len(table)
    assert [row[0] for row in body[-3:]] == [r"sift\_100\%", r"e3cm \& co", r"dfm \#1"]
    # each measured number with its interval, as the CSV holds it
    measured = table[table["source"] == "measured"].reset_index(drop=True)
    first = measured.iloc[0]
    assert re.fullmatch(r"(\\textbf\{)?%.2f\}? \[%.2f, %.2f\]" % (first["h_acc@1"], first["h_acc@1_lo"], first["h_acc@1_hi"]),
                        body[-3][1]), body[-3][1]
    assert body[-3][4] == "15"  # a count: no interval, no bold
    # the best of each compared column in bold, and only it (ties at the printed precision all bold)
    for k, column in enumerate(header[1:], start=1):
        name = column.replace("\\_", "_")
        if name == "n_pairs":
            assert not any("textbf" in row[k] for row in body)
            continue
        best = round(table[name].max(), 2)
        bold = [row for row in body if row[k].startswith(r"\textbf{")]
        assert bold and all(float(row[k][8:].split("}")[0]) == best for row in bold), (column, bold)
        assert all(round(v, 2) < best for v, row in zip(table[name], body) if not row[k].startswith(r"\textbf{")
                   and v == v)


def test_table_command_writes_latex_pdf_plots_and_own_rows_only(tmp_path):
    result = invoke("table", *RUNS, "--out", tmp_path / "t", "--latex", "--no-paper", "--no-compare", "--format", "pdf")
    assert result.exit_code == 0, result.output
    table = pd.read_csv(tmp_path / "t.csv")
    assert set(table["source"]) == {"measured"} and len(table) == 3  # --no-paper: the runs' rows only
    tex = (tmp_path / "t.tex").read_text()
    assert len(rows_of(tex)) == 1 + 3 and r"\bottomrule" in tex
    plots = sorted(p.name for p in tmp_path.iterdir() if p.name.startswith("t_"))
    assert plots == ["t_h_acc.pdf", "t_mma.pdf"]
    assert all((tmp_path / name).read_bytes().startswith(b"%PDF") for name in plots)
    # the same plot twice is the same file: no creation date in it
    again = invoke("table", *RUNS, "--out", tmp_path / "u", "--no-paper", "--format", "pdf")
    assert again.exit_code == 0
    assert (tmp_path / "u_h_acc.pdf").read_bytes() == (tmp_path / "t_h_acc.pdf").read_bytes()


def test_svg_plots_parse_as_xml_and_a_bad_format_is_one_line(tmp_path):
    assert invoke("table", *RUNS, "--out", tmp_path / "t", "--format", "svg").exit_code == 0
    for name in ("t_h_acc.svg", "t_mma.svg"):
        assert ET.parse(tmp_path / name).getroot().tag.endswith("svg")
    bad = invoke("table", *RUNS, "--out", tmp_path / "b", "--format", "jpeg")
    assert bad.exit_code == 2 and "--format jpeg" in bad.stderr and "png, pdf, svg" in bad.stderr
    assert not (tmp_path / "b.csv").exists()


def test_default_plots_stay_png(tmp_path):
    assert invoke("table", *RUNS, "--out", tmp_path / "t").exit_code == 0
    assert (tmp_path / "t_h_acc.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not (tmp_path / "t.tex").exists()


@pytest.mark.skipif(shutil.which("pdflatex") is None, reason="no pdflatex (apt-get install texlive-latex-recommended)")
def test_latex_table_compiles(tmp_path):
    assert invoke("table", *RUNS, "--out", tmp_path / "t", "--latex").exit_code == 0
    (tmp_path / "doc.tex").write_text("\\documentclass{article}\n\\usepackage{booktabs}\n\\begin{document}\n"
                                      "\\input{t.tex}\n\\end{document}\n")
    done = subprocess.run(["pdflatex", "-interaction=nonstopmode", "-halt-on-error", "doc.tex"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout[-2000:]
    assert (tmp_path / "doc.pdf").read_bytes().startswith(b"%PDF")


def test_counts_and_descriptive_figures_are_never_bold():
    """An SfM table: the scores with intervals get a best, the counts (registered images, points)
    and the mean track length none; an error with an interval is best lowest."""
    table = pd.DataFrame({
        "method": ["a", "b"], "source": ["measured", "measured"],
        "auc@5": [90.0, 95.0], "auc@5_lo": [89.0, 94.0], "auc@5_hi": [91.0, 96.0],
        "registered_images": [10.0, 9.0], "points": [1716.0, 5633.0], "mean_track_length": [6.05, 3.21],
        "mean_reprojection_error": [0.18, 0.29], "mean_reprojection_error_lo": [0.1, 0.2],
        "mean_reprojection_error_hi": [0.2, 0.3], "confidence": [0.95, 0.95]})
    body = rows_of(table_to_latex(table))[1:]
    assert body[0] == ["a", "90.00 [89.00, 91.00]", "10", "1716", "6.05", r"\textbf{0.18} [0.10, 0.20]"]
    assert body[1] == ["b", r"\textbf{95.00} [94.00, 96.00]", "9", "5633", "3.21", "0.29 [0.20, 0.30]"]
