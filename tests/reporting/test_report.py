"""Reporting: run loading, paper tables, markdown, CSV writing, plots, and the transcribed paper numbers."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from rich.console import Console

from e3cm_bench.drawing import plots

from e3cm_bench.reporting import tables as report
from e3cm_bench.ground.files import write_csv
from e3cm_bench.geometry.metrics import pose_error_curve
from e3cm_bench.paper import PAPER_DIR

PAPER_METHODS = [
    "SIFT+NN", "NCNet", "LIFT", "R2D2+NN", "DRC-Net", "SOSNet", "MAGSAC",
    "Patch2pix", "SuperPoint+SuperGlue", "LoFTR", "DFM", "E3CM",
]
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def make_run(root: Path, name: str, config: dict, summary: dict, per_pair: pd.DataFrame | None) -> Path:
    run_dir = root / name
    run_dir.mkdir(parents=True)
    (run_dir / "config.yaml").write_text(yaml.safe_dump(config))
    pd.DataFrame([summary]).to_csv(run_dir / "summary.csv", index=False)
    if per_pair is not None:
        per_pair.to_csv(run_dir / "per_pair.csv", index=False)
    return run_dir


def pose_summary(auc5, auc10, auc20, precision, n_pairs=4, n_matches=500.0) -> dict:
    return {"n_pairs": n_pairs, "n_matches": n_matches, "auc@5": auc5, "auc@10": auc10, "auc@20": auc20,
            "precision@1e-4": precision, "precision@5e-4": precision + 3.0}


def pose_per_pair(errors) -> pd.DataFrame:
    n = len(errors)
    return pd.DataFrame({"pair": [f"p{i}" for i in range(n)], "n_matches": [500] * n, "err_R": errors,
                         "err_t": errors, "err_pose": errors, "precision@1e-4": [0.9] * n,
                         "precision@5e-4": [0.95] * n})


def hpatches_summary(h_acc, n_matches=1500.0, with_viewpoint=True) -> dict:
    summary = {"n_pairs": 10, "n_matches": n_matches}
    summary.update({f"mma@{t}": min(1.0, 0.3 + 0.07 * t) for t in range(1, 11)})
    summary.update({f"mma@{t}_i": min(1.0, 0.35 + 0.06 * t) for t in range(1, 11)})
    summary.update({f"mma@{t}_v": (min(1.0, 0.25 + 0.08 * t) if with_viewpoint else float("nan"))
                    for t in range(1, 11)})
    summary.update({"n_pairs_i": 5, "n_pairs_v": 5 if with_viewpoint else 0})
    summary.update({"h_acc@1": h_acc[0], "h_acc@3": h_acc[1], "h_acc@5": h_acc[2]})
    return summary


@pytest.fixture
def pose_runs(tmp_path) -> list[report.Run]:
    e3cm = make_run(tmp_path, "run_e3cm", {"benchmark": "megadepth", "method": "e3cm-release", "matcher": {"ratio": 0.9},
                                           "backbone": "vgg19", "identity": {"matcher": "e3cm-release", "settings": {}}},
                    pose_summary(40.0, 55.0, 66.0, 90.0), pose_per_pair([1.0, 3.0, 12.0, float("inf")]))
    sift = make_run(tmp_path, "run_sift", {"benchmark": "megadepth", "method": "sift", "matcher": {},
                                           "backbone": None, "identity": {"matcher": "sift"}},
                    pose_summary(5.0, 10.0, 20.0, 20.0), pose_per_pair([4.0, 25.0, float("inf"), float("inf")]))
    return [report.load_run(e3cm), report.load_run(sift)]


@pytest.fixture
def hpatches_run(tmp_path) -> report.Run:
    per_pair = pd.DataFrame({"pair": ["i_a/1-2", "v_b/1-2"], "sequence": ["i_a", "v_b"], "n_matches": [1400, 1600],
                             **{f"mma@{t}": [0.5, 0.6] for t in range(1, 11)}, "h_error": [0.8, float("inf")]})
    run_dir = make_run(tmp_path, "run_dfm", {"benchmark": "hpatches", "method": "dfm", "matcher": {},
                                             "identity": {"matcher": "dfm", "settings": {}}},
                       hpatches_summary((0.45, 0.70, 0.90)), per_pair)
    return report.load_run(run_dir)


# --------------------------------------------------------------------------- load_run


def test_load_run_reads_config_summary_and_per_pair(pose_runs):
    e3cm = pose_runs[0]
    assert e3cm.benchmark.name == "megadepth"
    assert e3cm.label == "e3cm-release"
    assert e3cm.config["matcher"] == {"ratio": 0.9}
    assert e3cm.summary["auc@5"] == 40.0
    assert e3cm.summary["n_pairs"] == 4
    assert len(e3cm.per_pair) == 4
    assert math.isinf(e3cm.per_pair["err_pose"].iloc[3])


def test_load_run_label_falls_back_to_folder_name(tmp_path):
    run_dir = make_run(tmp_path, "yfcc_2024", {"benchmark": "yfcc"}, pose_summary(1, 2, 3, 4), None)
    run = report.load_run(run_dir)
    assert run.label == "yfcc_2024"
    assert run.per_pair.empty


@pytest.mark.parametrize(
    "breakage, file_name",
    [
        (lambda d: (d / "summary.csv").unlink(), "summary.csv"),
        (lambda d: (d / "config.yaml").unlink(), "config.yaml"),
        (lambda d: (d / "config.yaml").write_text("- just\n- a list\n"), "config.yaml"),
        (lambda d: (d / "config.yaml").write_text("benchmark: [unclosed\n"), "config.yaml"),
        (lambda d: (d / "config.yaml").write_text("benchmark: scannet\n"), "config.yaml"),
        (lambda d: (d / "summary.csv").write_text(""), "summary.csv"),
        (lambda d: (d / "summary.csv").write_text("n_pairs,auc@5\n4,1.0\n"), "summary.csv"),
        (lambda d: pd.concat([pd.read_csv(d / "summary.csv")] * 2).to_csv(d / "summary.csv", index=False),
         "summary.csv"),
    ],
)
def test_load_run_rejects_broken_folders_naming_the_file(tmp_path, breakage, file_name):
    run_dir = make_run(tmp_path, "broken", {"benchmark": "megadepth", "method": "e3cm"},
                       pose_summary(1, 2, 3, 4), None)
    breakage(run_dir)
    with pytest.raises(ValueError) as excinfo:
        report.load_run(run_dir)
    message = str(excinfo.value)
    assert str(run_dir / file_name) in message
    assert "\n" not in message


# --------------------------------------------------------------------------- paper tables


def test_pose_paper_table_rows_columns_and_differences(pose_runs):
    table = report.paper_table(pose_runs, "megadepth", PAPER_DIR / "table2.csv")
    assert list(table.columns) == ["method", "source", "auc@5", "auc@10", "auc@20", "P", "n_pairs", "vs_paper",
                                   "protocol", "d_auc@5", "d_auc@10", "d_auc@20", "d_P", "outside_ci", "other_pairs", "cost_note",
                                   *(f"{m}_{b}" for m in ("auc@5", "auc@10", "auc@20", "P") for b in ("lo", "hi")),
                                   "confidence"]
    assert list(table["source"]) == ["paper"] * 12 + ["measured"] * 2
    assert list(table["method"]) == PAPER_METHODS + ["e3cm-release", "sift"]
    # The paper's E3CM numbers came from the released code: e3cm-release is compared with them.
    assert list(table["vs_paper"].iloc[12:]) == ["E3CM", "SIFT+NN"]

    e3cm = table.iloc[12]
    # measured - paper: (40, 55, 66, 90) - (39.85, 54.11, 65.86, 91.14)
    assert e3cm[["d_auc@5", "d_auc@10", "d_auc@20", "d_P"]].tolist() == pytest.approx([0.15, 0.89, 0.14, -1.14])
    assert e3cm["n_pairs"] == 4
    sift = table.iloc[13]
    # (5, 10, 20, 20) - SIFT+NN (4.78, 10.71, 20.44, 17.19)
    assert sift[["d_auc@5", "d_auc@10", "d_auc@20", "d_P"]].tolist() == pytest.approx([0.22, -0.71, -0.44, 2.81])
    assert table.iloc[:12][["d_auc@5", "n_pairs"]].isna().all().all()
    # 4 pairs against the paper's 1500: the differences are said to be over other pairs
    assert e3cm["other_pairs"] == "4 pairs; the paper: MegaDepth-1500 (1500 pairs)"


def test_hpatches_paper_table(hpatches_run):
    table = report.paper_table([hpatches_run], "hpatches", PAPER_DIR / "table1.csv")
    assert list(table.columns) == ["method", "source", "h_acc@1", "h_acc@3", "h_acc@5", "n_pairs", "mma@3",
                                   "vs_paper", "protocol", "d_h_acc@1", "d_h_acc@3", "d_h_acc@5", "outside_ci", "other_pairs", "cost_note",
                                   *(f"{m}_{b}" for m in ("h_acc@1", "h_acc@3", "h_acc@5", "mma@3") for b in ("lo", "hi")),
                                   "confidence"]
    measured = table[table["source"] == "measured"].iloc[0]
    # (0.45, 0.70, 0.90) - DFM (0.41, 0.74, 0.86), fractions
    assert measured[["d_h_acc@1", "d_h_acc@3", "d_h_acc@5"]].tolist() == pytest.approx([0.04, -0.04, 0.04])
    assert measured["mma@3"] == pytest.approx(0.51)


def test_paper_table_without_reference_or_matching_method(tmp_path):
    run_dir = make_run(tmp_path, "densenet", {"benchmark": "yfcc", "method": "e3cm-densenet161"},
                       pose_summary(18.0, 32.0, 46.0, 80.0), None)
    table = report.paper_table([report.load_run(run_dir)], "yfcc", PAPER_DIR / "table3.csv")
    assert table.iloc[-1]["method"] == "e3cm-densenet161"
    assert np.isnan(table.iloc[-1]["d_auc@5"])
    only_measured = report.paper_table([report.load_run(run_dir)], "yfcc", None)
    assert list(only_measured["source"]) == ["measured"]


def test_paper_text_e3cm_and_dfm_variants_have_no_paper_row(tmp_path):
    runs = []
    for name, identity in [("e3cm", {"matcher": "e3cm", "settings": {"estimator": "top8"}}),
                           ("dfm-corrected", {"matcher": "dfm", "settings": {"variant": "corrected"}}),
                           ("e3cm-release-uncascaded", {"matcher": "e3cm-release", "settings": {"cascade": False}})]:
        run_dir = make_run(tmp_path, name, {"benchmark": "megadepth", "method": name, "identity": identity},
                           pose_summary(40.0, 55.0, 66.0, 90.0), None)
        runs.append(report.load_run(run_dir))
    table = report.paper_table(runs, "megadepth", PAPER_DIR / "table2.csv")
    measured = table[table["source"] == "measured"]
    assert list(measured["vs_paper"]) == ["", "", ""]
    assert measured["d_auc@5"].isna().all()


def test_non_standard_protocol_is_flagged(tmp_path):
    run_dir = make_run(tmp_path, "rel", {"benchmark": "megadepth", "method": "e3cm-release",
                                         "identity": {"matcher": "e3cm-release", "settings": {"num_levels": 4}},
                                         "evaluation": {"protocol": "e3cm-release"}},
                       pose_summary(40.0, 55.0, 66.0, 90.0), None)
    table = report.paper_table([report.load_run(run_dir)], "megadepth", None)
    assert table.iloc[0]["method"] == "e3cm-release (non-standard)"
    assert table.iloc[0]["protocol"] == "e3cm-release"


def test_paper_table_rejects_mixed_benchmarks(pose_runs, hpatches_run):
    with pytest.raises(ValueError, match="run_dfm"):
        report.paper_table([*pose_runs, hpatches_run], "megadepth", None)


def test_method_key_matches_paper_names():
    assert report.method_key("sift") == report.method_key("SIFT+NN")
    assert report.method_key("e3cm") == report.method_key("E3CM (Ours)")
    assert report.method_key("dfm") == report.method_key("DFM")
    assert report.method_key("e3cm-densenet161") != report.method_key("E3CM")


def test_markdown_has_header_rule_and_formatted_rows(pose_runs):
    table = report.paper_table(pose_runs, "megadepth", PAPER_DIR / "table2.csv")
    markdown = report.table_to_markdown(table)
    lines = markdown.split("\n\n")[0].splitlines()  # the table; the notes on pair sets follow it
    assert len(lines) == 2 + len(table)
    assert "Note: e3cm-release is measured on 4 pairs, E3CM in the paper on MegaDepth-1500" in markdown
    # The interval columns are folded into their numbers' cells, not shown on their own.
    shown = [c for c in table.columns if not c.endswith(("_lo", "_hi"))
             and c not in ("outside_ci", "other_pairs", "cost_note", "confidence")]
    assert [cell.strip() for cell in lines[0].strip("|").split("|")] == shown
    assert set(lines[1]) <= {"|", "-", ":", " "}
    e3cm_paper = next(line for line in lines if line.startswith("| E3CM ") and "paper" in line)
    assert "39.85" in e3cm_paper and "91.14" in e3cm_paper
    e3cm_measured = next(line for line in lines if line.startswith("| e3cm-release ") and "measured" in line)
    assert "40.00" in e3cm_measured and "+0.15 (other pairs)" in e3cm_measured and "-1.14" in e3cm_measured
    assert "| 4 " in e3cm_measured or " 4 |" in e3cm_measured  # n_pairs printed as an integer


def test_write_paper_table_writes_csv_and_md(tmp_path, pose_runs):
    table = report.paper_table(pose_runs, "megadepth", PAPER_DIR / "table2.csv")
    csv_path, md_path = report.write_paper_table(table, tmp_path / "tables" / "megadepth")
    assert csv_path == tmp_path / "tables" / "megadepth.csv" and md_path.suffix == ".md"
    round_trip = pd.read_csv(csv_path)
    assert round_trip["d_auc@5"].iloc[12] == pytest.approx(0.15)
    assert md_path.read_text() == report.table_to_markdown(table)


# --------------------------------------------------------------------------- CSV writing and console


def test_write_csv_round_trips_inf_and_creates_parents(tmp_path):
    df = pd.DataFrame({"pair": ["a", "b"], "err_pose": [0.1 + 0.2, float("inf")]})
    path = write_csv(df, tmp_path / "deep" / "per_pair.csv")
    assert path.read_text().splitlines() == ["pair,err_pose", "a,0.3", "b,inf"]
    assert math.isinf(pd.read_csv(path)["err_pose"].iloc[1])


def test_interrupted_write_leaves_the_old_csv_intact(tmp_path, monkeypatch):
    path = write_csv(pd.DataFrame({"x": [1.0]}), tmp_path / "summary.csv")
    before = path.read_text()

    def write_half_then_fail(self, target, **kwargs):
        Path(target).write_text("x\n")
        raise KeyboardInterrupt

    monkeypatch.setattr(pd.DataFrame, "to_csv", write_half_then_fail)
    with pytest.raises(KeyboardInterrupt):
        write_csv(pd.DataFrame({"x": [2.0, 3.0]}), path)
    assert path.read_text() == before
    assert [p.name for p in tmp_path.iterdir()] == ["summary.csv"]  # no temporary file left behind


def test_print_summary_shows_splits_side_by_side(hpatches_run):
    console = Console(record=True, width=120)
    report.print_summary(hpatches_run.summary, "HPatches dfm", console=console)
    text = console.export_text()
    assert "HPatches dfm" in text and "illumination" in text and "viewpoint" in text
    mma1_row = next(line for line in text.splitlines() if "mma@1 " in line)
    assert "0.3700" in mma1_row and "0.4100" in mma1_row and "0.3300" in mma1_row
    assert "1.0000" in next(line for line in text.splitlines() if "mma@10 " in line)
    assert "mma@1_i" not in text
    assert "h_acc@5" in text


def test_print_summary_pose_is_metric_value(pose_runs):
    console = Console(record=True, width=100)
    report.print_summary(pose_runs[0].summary, "MegaDepth e3cm", console=console)
    text = console.export_text()
    assert "value" in text and "auc@5" in text and "40" in text


# --------------------------------------------------------------------------- plots


def assert_png(path: Path) -> None:
    assert path.is_file() and path.stat().st_size > 1000
    assert path.read_bytes()[:8] == PNG_SIGNATURE


def test_pose_error_curve_counts_failures_in_the_denominator():
    x, y = pose_error_curve([12.0, 1.0, float("inf"), 3.0])
    assert x.tolist() == [0.0, 1.0, 3.0, 12.0]
    assert y.tolist() == [0.0, 0.25, 0.5, 0.75]


def test_plot_mma_curves_several_runs_and_single_run_with_nan_split(tmp_path, hpatches_run):
    several = {"dfm": hpatches_run.summary, "e3cm": hpatches_summary((0.5, 0.8, 0.9), n_matches=2100.0)}
    assert_png(plots.plot_mma_curves(several, tmp_path / "mma.png"))
    fig = plots.mma_figure(several)
    axes = fig.axes
    assert [ax.get_title() for ax in axes] == ["Overall", "Illumination", "Viewpoint"]
    # One line per run in each panel, drawn through the run's MMA values at 1..10 px.
    for ax, suffix in zip(axes, ("", "_i", "_v")):
        lines = {line.get_label(): line for line in ax.get_lines()}
        assert set(lines) == {"dfm", "e3cm"}
        assert lines["e3cm"].get_xdata().tolist() == list(range(1, 11))
        expected = [several["e3cm"][f"mma@{t}{suffix}"] for t in range(1, 11)]
        assert lines["e3cm"].get_ydata().tolist() == pytest.approx(expected)
    legend = [text.get_text() for text in fig.legends[0].get_texts()]
    assert legend == [f"dfm ({hpatches_run.summary['n_matches']:.0f} matches)", "e3cm (2100 matches)"]

    illumination_only = {"e3cm": hpatches_summary((0.5, 0.8, 0.9), with_viewpoint=False)}
    assert_png(plots.plot_mma_curves(illumination_only, tmp_path / "plots" / "mma_single.png"))
    viewpoint = plots.mma_figure(illumination_only).axes[2]
    assert viewpoint.get_lines() == [] and [t.get_text() for t in viewpoint.texts] == ["no pairs"]


def test_plot_pose_error_cdf(tmp_path, pose_runs):
    runs = {run.label: run.per_pair for run in pose_runs}
    assert_png(plots.plot_pose_error_cdf(runs, tmp_path / "cdf.png"))
    ax = plots.pose_error_cdf_figure(runs).axes[0]
    for run in pose_runs:
        (line,) = [l for l in ax.get_lines() if l.get_label().startswith(run.label + " (")]
        errors = run.per_pair["err_pose"].to_numpy(float)
        n_failed = int((~np.isfinite(errors)).sum())
        assert line.get_label() == f"{run.label} ({len(errors)} pairs, {n_failed} failed)"
        x, y = pose_error_curve(errors)
        # The curve's points, held flat to the right edge (30 deg).
        assert line.get_xdata().tolist() == pytest.approx([*x.tolist(), max(30.0, x[-1])])
        assert line.get_ydata().tolist() == pytest.approx([*y.tolist(), y[-1]])
    with pytest.raises(ValueError, match="err_pose"):
        plots.plot_pose_error_cdf({"empty": pd.DataFrame()}, tmp_path / "bad.png")


def test_plot_pose_auc_bars(tmp_path, pose_runs):
    runs = {run.label: run.summary for run in pose_runs}
    assert_png(plots.plot_pose_auc_bars(runs, tmp_path / "auc.png", "MegaDepth-1500"))
    fig = plots.pose_auc_figure(runs, "MegaDepth-1500")
    auc_ax, precision_ax = fig.axes
    heights = [bar.get_height() for bar in auc_ax.patches]
    expected = [run.summary[f"auc@{t}"] for run in pose_runs for t in (5, 10, 20)]
    assert heights == pytest.approx(expected)  # bars are drawn run by run
    assert [bar.get_height() for bar in precision_ax.patches] == pytest.approx([r.summary["precision@1e-4"] for r in pose_runs])
    assert [t.get_text() for t in precision_ax.get_xticklabels()] == [run.label for run in pose_runs]
    assert fig._suptitle.get_text().startswith("MegaDepth-1500; bars: 95% bootstrap interval")


# --------------------------------------------------------------------------- transcribed paper tables

# PROTOCOLS.md §4: the anchors to reproduce.
PROTOCOL_ANCHORS = {
    "table1.csv": {"DFM": [0.41, 0.74, 0.86], "E3CM": [0.49, 0.78, 0.88], "SIFT+NN": [0.36, 0.76, 0.85]},
    "table2.csv": {"DFM": [35.17, 50.64, 61.12, 77.19], "E3CM": [39.85, 54.11, 65.86, 91.14],
                   "SIFT+NN": [4.78, 10.71, 20.44, 17.19]},
    "table3.csv": {"DFM": [15.30, 28.57, 42.91, 61.68], "E3CM": [17.63, 31.07, 45.51, 76.61],
                   "SIFT+NN": [4.67, 12.04, 24.33, 12.04]},
}


@pytest.mark.parametrize("file_name", sorted(PROTOCOL_ANCHORS))
def test_transcribed_tables_match_protocol_anchors(file_name):
    table = pd.read_csv(PAPER_DIR / file_name)
    assert list(table["method"]) == PAPER_METHODS
    assert len(table) == 12 and not table.isna().any().any()
    metrics = ["h_acc@1", "h_acc@3", "h_acc@5"] if file_name == "table1.csv" else ["auc@5", "auc@10", "auc@20", "P"]
    assert list(table.columns) == ["method", "category", *metrics]
    assert set(table["category"]) == {"training-free", "fully supervised", "plug-and-play"}
    by_method = table.set_index("method")
    for method, expected in PROTOCOL_ANCHORS[file_name].items():
        assert by_method.loc[method, metrics].tolist() == pytest.approx(expected)
