"""`e3cm-bench demo` end to end at reduced size, and the `check` regression command."""

from __future__ import annotations

import shutil
from pathlib import Path

import pandas as pd
import pytest
import torch
import yaml

from e3cm_bench.apps.demo import METHODS as DEMO_METHODS
from helpers import flat, invoke, one_line_error

REPO_ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory) -> tuple[Path, str]:
    """The quick demo (1 viewpoint and 1 illumination sequence, 2 scene pairs) with one deep
    method and SIFT, and what it printed."""
    out = tmp_path_factory.mktemp("demo") / "e3cm-demo"
    result = invoke("demo", "--out", out, "--quick", "--methods", "e3cm-ransac,sift")
    assert result.exit_code == 0, (result.output, result.exception)
    return out, result.output


@pytest.fixture(scope="module")
def demo_out(demo_run) -> Path:
    return demo_run[0]


@pytest.mark.slow  # the quick demo they read: 396 s alone on a loaded 2-core machine (CI runs the demo too)
def test_demo_prints_a_short_account_and_logs_the_rest(demo_run):
    """A line per set and per method with its headline numbers, the tables within 80 columns,
    each message (the sets, the orderings, the files) one whole line in a pipe; the runs' own
    tables go to demo.log."""
    out, output = demo_run
    lines = output.splitlines()
    rows = [line for line in lines if line.startswith("  ")]  # the sets' tables
    assert len(lines) <= 30 and rows and max(map(len, rows)) <= 80, output
    # the orderings, then the files: each one whole line (none broken mid-sentence)
    after = lines[lines.index("The paper's orderings on these data:") + 1:]
    assert after and after[-1].startswith("demo: tables, plots and match drawings under ") and after[-1].endswith(")")
    assert all(line.startswith("- ") and (line.endswith(")") or "none judged" in line) for line in after[:-1]), output
    assert "10 pairs (5 illumination, 5 viewpoint)" in output
    table = pd.read_csv(out / "hpatches_table.csv").set_index("method")
    for method in ("e3cm-ransac", "sift"):
        hpatches_line, scenes_line = [line for line in lines if line.split()[:1] == [method]]
        lo, hi = table.loc[method, "h_acc@1_lo"], table.loc[method, "h_acc@1_hi"]
        assert hpatches_line.split()[1:3] == [f"{table.loc[method, 'h_acc@1']:.2f}", f"[{lo:.2f},{hi:.2f}]"]
    log = (out / "demo.log").read_text()
    # each run's table, then the set's table (in column blocks that fit 80 columns) with its files
    assert "hpatches - sift (10 pairs)" in log and "hpatches_table.md" in log
    assert any(line.split()[:2] == ["method", "source"] for line in log.splitlines())
    assert "hpatches - sift" not in output


def test_demo_help_names_every_method_it_runs():
    result = invoke("demo", "--help", terminal_width=200)
    assert result.exit_code == 0
    description = flat(result.output.split("Options")[0])  # the command's help, not --methods' choices
    assert all(method in description for method in DEMO_METHODS), description


@pytest.mark.slow  # the quick demo they read: 396 s alone on a loaded 2-core machine (CI runs the demo too)
def test_demo_writes_data_runs_tables_and_pictures(demo_out):
    # The data, in the real layouts.
    assert sorted(p.name for p in (demo_out / "data" / "hpatches").iterdir()) == ["i_hopper1", "v_hopper1"]
    assert (demo_out / "data" / "scenes" / "pairs_with_gt.txt").read_text().count("\n") == 2
    for set_name, n_pairs, metric in (("hpatches", 10, "h_acc@3"), ("scenes", 2, "auc@10")):
        table = pd.read_csv(demo_out / f"{set_name}_table.csv")
        assert list(table["method"]) == ["e3cm-ransac", "sift"] and set(table["source"]) == {"measured"}
        assert (table["n_pairs"] == n_pairs).all() and table[metric].notna().all()
        assert not any(c.startswith("d_") for c in table.columns)  # no paper comparison on these data
        assert (demo_out / f"{set_name}_table.md").is_file()
        for method in ("e3cm-ransac", "sift"):
            run = demo_out / set_name / method
            assert (run / "summary.csv").is_file() and len(list((run / "viz").glob("*.png"))) == 2
    # --viz 2 draws a spread: an illumination and a viewpoint pair, not the first two of one sequence
    assert sorted(p.name[0] for p in (demo_out / "hpatches" / "sift" / "viz").glob("*.png")) == ["i", "v"]
    hpatches = pd.read_csv(demo_out / "hpatches_table.csv").set_index("method")
    assert hpatches.loc["e3cm-ransac", "mma@3"] > 0.5 and hpatches.loc["sift", "mma@3"] > 0.5
    assert (demo_out / "hpatches_table_mma.png").is_file() and (demo_out / "scenes_table_pose_auc.png").is_file()
    assert (demo_out / "hpatches_table_h_acc.png").is_file()
    # Orderings that need e3cm, direct or dfm are not claimed when those did not run.
    assert (demo_out / "orderings.md").read_text().startswith("- none judged")


@pytest.mark.slow  # the quick demo they read: 396 s alone on a loaded 2-core machine (CI runs the demo too)
def test_demo_rerun_reuses_data_and_matches(demo_out):
    result = invoke("demo", "--out", demo_out, "--quick", "--methods", "sift")
    assert result.exit_code == 0
    log = (demo_out / "demo.log").read_text()  # this run's
    assert flat(log).count("found in") == 2 and "matching (" not in log


@pytest.mark.slow  # the quick demo they read: 396 s alone on a loaded 2-core machine (CI runs the demo too)
def test_runs_record_their_environment_which_does_not_block_a_resume(demo_out, tmp_path):
    """config.yaml's versions and environment say where the numbers were made; a folder made
    elsewhere (or before the environment was recorded) still resumes, and gets this one's."""
    config = yaml.safe_load((demo_out / "hpatches" / "sift" / "config.yaml").read_text())
    assert config["environment"]["cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    assert config["environment"]["threads"] == torch.get_num_threads()
    out = tmp_path / "e3cm-demo"
    shutil.copytree(demo_out, out)
    for set_name in ("hpatches", "scenes"):
        path = out / set_name / "sift" / "config.yaml"
        old = yaml.safe_load(path.read_text())
        del old["environment"]
        old["versions"] = {**old["versions"], "torch": "1.0.0", "numpy": "1.0.0"}
        path.write_text(yaml.safe_dump(old, sort_keys=False))
    result = invoke("demo", "--out", out, "--quick", "--methods", "sift")
    log = (out / "demo.log").read_text()
    assert result.exit_code == 0 and flat(log).count("found in") == 2 and "matching (" not in log
    for set_name in ("hpatches", "scenes"):
        config = yaml.safe_load((out / set_name / "sift" / "config.yaml").read_text())
        assert config["environment"]["torch"] == torch.__version__ and config["versions"]["numpy"] != "1.0.0"


def test_demo_rejects_unknown_methods(tmp_path):
    line = one_line_error(invoke("demo", "--out", tmp_path / "d", "--methods", "e3cm,superglue"))
    assert "superglue" in line and "e3cm-ransac" in line


@pytest.fixture
def checked(demo_out, tmp_path) -> tuple[Path, Path]:
    """A copy of the demo's hpatches runs and a baseline written from them."""
    runs = tmp_path / "runs"
    shutil.copytree(demo_out / "hpatches", runs)
    baseline = tmp_path / "baseline.csv"
    result = invoke("check", runs, "--baseline", baseline, "--update")
    assert result.exit_code == 0 and "2 runs written" in flat(result.output)
    table = pd.read_csv(baseline)
    assert list(table.columns) == ["benchmark", "method", "h_acc@1", "h_acc@3", "h_acc@5", "mma@3", "environment",
                                   "identity", "protocol_items"]
    assert len(pd.read_csv(tmp_path / "baseline.pairs.csv")) == 2 * pd.read_csv(runs / "sift" / "per_pair.csv").shape[0]
    assert table["environment"].str.contains(f"; torch={torch.__version__}; ", regex=False).all()
    assert table["environment"].str.contains(f"; cpu={torch.backends.cpu.get_cpu_capability()}; ", regex=False).all()
    return runs, baseline


def degrade(run: Path, column: str, by: float) -> None:
    """A run whose summary moved by `by`; its per_pair.csv is removed, since pairs that no longer
    give the summary are a problem check reports on their own."""
    summary = pd.read_csv(run / "summary.csv")
    summary[column] = summary[column] + by
    summary.to_csv(run / "summary.csv", index=False)
    (run / "per_pair.csv").unlink(missing_ok=True)


@pytest.mark.slow  # the quick demo they read: 396 s alone on a loaded 2-core machine (CI runs the demo too)
def test_check_passes_on_equal_summaries(checked, tmp_path):
    runs, baseline = checked
    report = tmp_path / "summary.md"
    result = invoke("check", runs, "--baseline", baseline, "--summary", report)
    assert result.exit_code == 0 and "no regression" in flat(result.output)
    text = report.read_text()
    assert "8 metrics checked: 0 regression(s)" in text and "| hpatches | sift | mma@3 |" in text


@pytest.mark.slow  # the quick demo they read: 396 s alone on a loaded 2-core machine (CI runs the demo too)
def test_check_fails_naming_each_metric_that_fell(checked, tmp_path):
    runs, baseline = checked
    degrade(runs / "sift", "mma@3", -0.05)  # tolerance 0.01
    degrade(runs / "e3cm-ransac", "h_acc@1", -0.2)  # tolerance 0.07
    degrade(runs / "e3cm-ransac", "h_acc@5", -0.05)  # within tolerance: not a regression
    report = tmp_path / "summary.md"
    result = invoke("check", runs, "--baseline", baseline, "--summary", report)
    assert result.exit_code == 1
    text = flat(result.output)
    assert "regression: sift on hpatches: mma@3" in text and "regression: e3cm-ransac on hpatches: h_acc@1" in text
    assert "h_acc@5" not in text and "2 regression(s)/problem(s)" in text
    assert "**regression**" in report.read_text()
    # A looser tolerance for one metric, given on the command line, lets it pass.
    result = invoke("check", runs, "--baseline", baseline, "--tolerance", "mma@3=0.1", "--tolerance", "h_acc@1=0.25")
    assert result.exit_code == 0


@pytest.mark.slow  # the quick demo they read: 396 s alone on a loaded 2-core machine (CI runs the demo too)
def test_check_reports_a_rise_as_a_notice(checked):
    runs, baseline = checked
    degrade(runs / "sift", "mma@3", +0.05)
    result = invoke("check", runs, "--baseline", baseline)
    assert result.exit_code == 0 and "improvement: sift on hpatches: mma@3" in flat(result.output)


@pytest.mark.slow  # the quick demo they read: 396 s alone on a loaded 2-core machine (CI runs the demo too)
def test_check_missing_runs_and_bad_options(checked, tmp_path):
    runs, baseline = checked
    shutil.rmtree(runs / "sift")
    result = invoke("check", runs, "--baseline", baseline)
    assert result.exit_code == 1 and "sift on hpatches has no run among those checked" in flat(result.output)
    line = one_line_error(invoke("check", runs, "--baseline", baseline, "--tolerance", "mma@3"))
    assert "METRIC=VALUE" in line
    line = one_line_error(invoke("check", runs, "--baseline", tmp_path / "none.csv"))
    assert "none.csv" in line and "--update" in line
    line = one_line_error(invoke("check", tmp_path / "empty-dir-missing", "--baseline", baseline))
    assert "not a folder" in line


def test_committed_baselines_cover_the_demo():
    """results/baselines/ holds one row per demo method and set (written by check --update)."""
    for set_name, benchmark in (("hpatches", "hpatches"), ("scenes", "yfcc")):
        table = pd.read_csv(REPO_ROOT / "results" / "baselines" / f"demo_{set_name}.csv")
        assert sorted(table["method"]) == sorted(DEMO_METHODS)
        assert set(table["benchmark"]) == {benchmark} and not table.drop(columns=["benchmark", "method"]).isna().any().any()
        # and beside it the per-pair baseline and the noise ensemble the check gates with
        pairs = pd.read_csv(REPO_ROOT / "results" / "baselines" / f"demo_{set_name}.pairs.csv")
        noise = pd.read_csv(REPO_ROOT / "results" / "baselines" / f"demo_{set_name}.noise.csv")
        assert sorted(pairs["method"].unique()) == sorted(DEMO_METHODS)
        assert len(noise) == noise["draw"].nunique() * len(pairs) and noise["draw"].nunique() >= 10
