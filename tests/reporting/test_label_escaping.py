"""Labels are text in every Markdown and HTML file the reports write (reporting/escape.py).

A label is the user's (`--label`, a config's method): `sift | ok` once split the Markdown row of
`check --summary`, so that "regression" left its column, and `<b>x</b>` or `[a](http://x)`
went raw into every .md as HTML and links."""

from __future__ import annotations

import re
from pathlib import Path

import pandas as pd
import pytest

from e3cm_bench.reporting.escape import html_text, markdown_code, markdown_text
from helpers import invoke
from test_check_env import write_run

PIPE, HTML, LINK = "sift | ok", "<b>x</b>", "[a](http://x)"


def cells(row: str) -> list[str]:
    """The cells of a Markdown table row as GitHub splits them: at every | not escaped."""
    return [c.strip() for c in re.split(r"(?<!\\)\|", row.strip())[1:-1]]


def rendered_free_of_markup(text: str) -> bool:
    """No raw tag or link syntax survives: every <, [ and ] in the text is escaped."""
    return not re.search(r"(?<!\\)[<\[\]]", text)


def _runs(tmp_path: Path) -> tuple[Path, Path]:
    root = tmp_path / "runs"
    for k, label in enumerate((PIPE, HTML, LINK)):
        write_run(root / f"r{k}", label)
    baseline = tmp_path / "baseline.csv"
    assert invoke("check", root, "--baseline", baseline, "--update").exit_code == 0
    return root, baseline


def test_check_summary_keeps_a_piped_label_in_one_cell(tmp_path):
    root, baseline = _runs(tmp_path)
    write_run(root / "r0", PIPE, h_acc1=0.2)  # h_acc@1 0.6 -> 0.2: a regression of `sift | ok`
    report = tmp_path / "summary.md"
    result = invoke("check", root, "--baseline", baseline, "--summary", report)
    assert result.exit_code == 1
    text = report.read_text()
    header = next(line for line in text.splitlines() if line.startswith("| benchmark"))
    rows = [cells(line) for line in text.splitlines() if line.startswith("| hpatches")]
    status = cells(header).index("status")
    assert all(len(row) == len(cells(header)) for row in rows)  # no row shifted
    flagged = [row for row in rows if row[status] == "**regression**"]
    assert len(flagged) == 1 and flagged[0][1] == r"sift \| ok" and flagged[0][2] == "h_acc@1"
    assert rendered_free_of_markup(text.split("\n", 1)[1])  # the heading's path is a code span


def test_table_markdown_keeps_labels_as_text(tmp_path):
    root, _ = _runs(tmp_path)
    result = invoke("table", *(root / f"r{k}" for k in range(3)), "--out", tmp_path / "t", "--no-compare")
    assert result.exit_code == 0, result.output
    text = (tmp_path / "t.md").read_text()
    lines = [line for line in text.splitlines() if line.startswith("|")]
    widths = {len(cells(line)) for line in lines}
    assert len(widths) == 1  # every row as many cells as the header
    method = cells(lines[0]).index("method")
    labels = {cells(line)[method] for line in lines[2:]}
    assert {r"sift \| ok", r"\<b>x\</b>", r"\[a\](http://x)"} <= labels
    assert rendered_free_of_markup(text)  # no raw tag, no link


def test_report_page_shows_labels_as_text(tmp_path):
    """The HTML report escaped labels already; held here with the Markdown writers."""
    root, _ = _runs(tmp_path)
    for k in range(3):  # the report reads each run's pairs too
        pd.DataFrame([{"pair": "v_x/1-2", "n_matches": 800, "h_error": 1.0, **{f"mma@{t}": 0.5 for t in range(1, 11)}}]
                     ).to_csv(root / f"r{k}" / "per_pair.csv", index=False)
    result = invoke("report", *(root / f"r{k}" for k in range(3)), "--out", tmp_path / "site", "--no-compare")
    if result.exit_code != 0:
        raise AssertionError(result.output)
    page = (tmp_path / "site" / "index.html").read_text()
    assert "<b>x</b>" not in page and html_text(HTML) in page and html_text(PIPE) in page


def test_the_escaping_functions():
    assert markdown_text(PIPE) == r"sift \| ok"
    assert markdown_text("a\nb") == "a b"  # a row is one line
    assert markdown_text("direct-efficientnet_lite0 (x)") == "direct-efficientnet_lite0 (x)"  # readable as it was
    assert markdown_code("a`b") == "``a`b``" and markdown_code("`x") == "`` `x ``"
    assert html_text('<a href="x">') == "&lt;a href=&quot;x&quot;&gt;"


@pytest.mark.parametrize("label", ["two\nlines", "tab\there"])
def test_a_label_is_one_line_of_printable_text(tmp_path, label):
    """A label is a table's row, a legend and a file name: a newline in it was accepted (issue 70)."""
    from helpers import one_line_error

    line = one_line_error(invoke("hpatches", "--root", tmp_path, "--out", tmp_path / "r", "--matcher", "sift",
                                 "--label", label))
    assert "--label must be one line of printable text" in line
