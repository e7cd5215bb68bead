"""A bootstrap interval on every number a run reports, and `e3cm-bench compare`.

A small SIFT run on the real HPatches sample gives a real summary.csv; the rest are run
folders written here with per-pair values chosen so that the expected answer is known.
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from e3cm_bench.benchmarks import intervals

from e3cm_bench.reporting import tables as report
from e3cm_bench.benchmarks import get_benchmark
from e3cm_bench.reporting.compare import compare_runs, parse_mma
from e3cm_bench.pipeline.experiments import write_table
from e3cm_bench.paper import PAPER_DIR
from helpers import invoke, one_line_error


def ok(*args):
    result = invoke(*args)
    assert result.exit_code == 0, (result.exit_code, result.output, result.exception)
    return result


@pytest.fixture(scope="module")
def sift_run(shared_data: Path, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("intervals") / "sift"
    # --interval-seeds 1: the pairs-only interval these tests rebuild from per_pair.csv (the seeds'
    # interval is tests/benchmarks/test_interval_seeds.py's)
    ok("hpatches", "--root", shared_data / "hpatches-sequences-release", "--out", out, "--matcher", "sift",
       "--max-side", 320, "--interval-seeds", 1)
    return out


def hpatches_rows(h_error, sequences=None, mma=0.5) -> pd.DataFrame:
    n = len(h_error)
    sequences = sequences or [("i_a" if k % 2 else "v_b") for k in range(n)]
    return pd.DataFrame({"pair": [f"{s}/1-{k + 2}" for k, s in enumerate(sequences)], "sequence": sequences,
                         "n_matches": [100 + k for k in range(n)],
                         **{f"mma@{t}": [mma] * n for t in range(1, 11)}, "h_error": h_error})


def write_run(folder: Path, benchmark: str, per_pair: pd.DataFrame, method: str = "sift", intervals_too: bool = True,
              identity: dict | None = None) -> Path:
    """A run folder as a run writes it: summary from the per-pair rows (with intervals, or as
    written before them)."""
    folder.mkdir(parents=True)
    bench = get_benchmark(benchmark)
    ev = bench.eval_settings()
    rows = per_pair.to_dict("records")
    summary = bench.summarize(rows, ev)
    if intervals_too:
        summary.update(intervals.summary_intervals(bench, rows, ev, summary=summary))
    config = {"benchmark": benchmark, "method": method, "identity": identity or {"matcher": method, "settings": {}},
              "evaluation": {"seed": 0}}
    (folder / "config.yaml").write_text(yaml.safe_dump(config))
    pd.DataFrame([summary]).to_csv(folder / "summary.csv", index=False)
    per_pair.to_csv(folder / "per_pair.csv", index=False)
    return folder


# --------------------------------------------------------------------------- the summary's intervals


def test_summary_holds_an_interval_around_every_metric(sift_run):
    summary = pd.read_csv(sift_run / "summary.csv").iloc[0]
    metrics = [k for k in summary.index if not intervals.is_interval_key(k) and not k.startswith(("n_pairs", "n_skipped"))
               and k not in intervals.PEAKS and k != "fingerprint"]
    assert "h_acc@1" in metrics and "mma@3_v" in metrics and "n_matches" in metrics
    for key in metrics:
        lo, hi = summary[f"{key}_lo"], summary[f"{key}_hi"]
        assert lo <= summary[key] <= hi, (key, lo, summary[key], hi)
    assert "n_pairs_lo" not in summary.index and "n_pairs_i_hi" not in summary.index  # counts have none
    assert (summary["bootstrap_samples"], summary["bootstrap_seed"], summary["confidence"]) == (1000, 0, 0.95)
    # 15 pairs: the interval of a fraction of pairs is wide, not a point
    assert summary["mma@3_hi"] - summary["mma@3_lo"] > 0.01
    # every column a reader indexed before is still there, a number, in its place
    point = [k for k in summary.index if not intervals.is_interval_key(k)]
    assert point[:12] == ["n_pairs", "n_matches", *[f"mma@{t}" for t in range(1, 11)]] and point[-7:] == [
        "h_acc@1", "h_acc@3", "h_acc@5", "seconds_per_pair", "peak_memory_mb", "cache_memory_mb",  # the run's cost
        "fingerprint"]  # then what it was scored under (storage/fingerprint.py)


def test_the_intervals_are_deterministic_for_the_seed(sift_run):
    summary = pd.read_csv(sift_run / "summary.csv").iloc[0].to_dict()
    bench = get_benchmark("hpatches")
    rows = pd.read_csv(sift_run / "per_pair.csv").to_dict("records")
    again = intervals.summary_intervals(bench, rows, bench.eval_settings())
    for key, value in again.items():
        assert value == pytest.approx(summary[key], rel=1e-6, abs=1e-9), key  # summary.csv holds 8 digits
    other = intervals.summary_intervals(bench, rows, bench.eval_settings(), seed=1)
    assert other["bootstrap_seed"] == 1
    assert any(other[k] != again[k] for k in again if k.endswith(("_lo", "_hi")))


@pytest.mark.parametrize("benchmark", ["hpatches", "megadepth"])
@pytest.mark.parametrize("drop_failures", [False, True])
def test_the_array_summary_is_the_summary_bit_for_bit(benchmark, drop_failures):
    """Each benchmark's indexed_summary (the bootstrap's fast path) equals summarize on the same rows."""
    rng = np.random.default_rng(3)
    n = 40
    bench = get_benchmark(benchmark)
    ev = bench.eval_settings(drop_failures=drop_failures)
    if benchmark == "hpatches":
        errors = np.where(rng.random(n) < 0.2, np.inf, rng.exponential(3, n))
        frame = hpatches_rows(list(errors), sequences=[["i_a", "v_b", "x_c"][k % 3] for k in range(n)])
        for t in range(1, 11):
            frame[f"mma@{t}"] = rng.random(n)
    else:
        frame = pd.DataFrame({"pair": [f"p{k}" for k in range(n)], "n_matches": rng.integers(0, 900, n),
                              "err_R": 1.0, "err_t": 1.0,
                              "err_pose": np.where(rng.random(n) < 0.2, np.inf, rng.exponential(8, n)),
                              "precision@1e-4": rng.random(n), "precision@5e-4": rng.random(n)})
    rows = frame.to_dict("records")
    fast = bench.indexed_summary(rows, ev)
    for idx in [range(n), *(rng.integers(0, n, n) for _ in range(30)), [0], [k for k in range(n) if k % 3 == 0]]:
        got, want = fast(idx), bench.summarize([rows[i] for i in idx], ev)
        assert list(got) == list(want)
        for key in want:
            assert got[key] == want[key] or (math.isnan(got[key]) and math.isnan(want[key])), key


def test_the_bootstrap_of_the_array_summary_is_that_of_the_rows():
    bench = get_benchmark("hpatches")
    rows = hpatches_rows([0.5, 2.0, 4.0, np.inf, 0.9, 7.0, 1.5, 0.2]).to_dict("records")
    ev = bench.eval_settings()
    from e3cm_bench import stats

    keys = intervals.metric_keys(bench.summarize(rows, ev))
    slow = stats.bootstrap_interval(rows, lambda r: bench.summarize(r, ev), n_samples=200, keys=keys)
    fast = intervals.summary_intervals(bench, rows, ev, n_samples=200)
    for key in keys:
        assert (fast[f"{key}_lo"], fast[f"{key}_hi"]) == pytest.approx(slow[key], nan_ok=True), key


def test_print_summary_shows_each_number_with_its_interval(sift_run):
    from rich.console import Console

    summary = report.load_run(sift_run).summary
    console = Console(record=True, width=200)
    report.print_summary(summary, "sift", console=console)
    text = console.export_text()
    line = next(line for line in text.splitlines() if " h_acc@1 " in line)
    assert f"{summary['h_acc@1']:.4f} [{summary['h_acc@1_lo']:.4f}, {summary['h_acc@1_hi']:.4f}]" in line
    assert "_lo" not in text and "bootstrap_seed" not in text and "95% bootstrap interval" in text


# --------------------------------------------------------------------------- tables


def test_a_paper_number_outside_the_interval_is_flagged(tmp_path):
    """Every pair under 1 px: h_acc@t = 1 with the interval [1, 1], so the paper's SIFT+NN numbers
    (0.36, 0.76, 0.85) all lie outside it; a number whose interval holds the paper's is not flagged.
    Runs of the paper's size (540 pairs): on fewer pairs the sets differ and nothing is flagged
    (test_compare_check.py)."""
    flagged = write_run(tmp_path / "sift", "hpatches", hpatches_rows([0.5] * 540))
    table = report.paper_table([report.load_run(flagged)], "hpatches", PAPER_DIR / "table1.csv")
    row = table[table["source"] == "measured"].iloc[0]
    assert row["vs_paper"] == "SIFT+NN" and (row["h_acc@1_lo"], row["h_acc@1_hi"]) == (1.0, 1.0)
    assert row["outside_ci"] == "h_acc@1, h_acc@3, h_acc@5"
    markdown = report.table_to_markdown(table)
    line = next(line for line in markdown.splitlines() if line.startswith("| sift "))
    assert "+0.64 (outside 95% CI)" in line and "1.00 [1.00, 1.00]" in line
    paper_line = next(line for line in markdown.splitlines() if line.startswith("| SIFT+NN "))
    assert "[" not in paper_line and "outside" not in paper_line  # the paper's rows have no interval

    # 194 of 540 pairs under 1 px, the others between 1 and 3: h_acc@1 0.359 with an interval around
    # it that holds the paper's 0.36; h_acc@3 = h_acc@5 = 1, which the paper's 0.76 and 0.85 are outside
    inside = write_run(tmp_path / "sift2", "hpatches", hpatches_rows([0.5] * 194 + [2.0] * 346))
    row = report.paper_table([report.load_run(inside)], "hpatches", PAPER_DIR / "table1.csv").iloc[-1]
    assert row["h_acc@1_lo"] <= 0.36 <= row["h_acc@1_hi"]
    assert row["outside_ci"] == "h_acc@3, h_acc@5"


def test_write_table_carries_the_intervals_and_drops_the_flag_without_compare(sift_run, tmp_path):
    csv_path, md_path = write_table([sift_run], tmp_path / "table", compare=False)
    table = pd.read_csv(csv_path)
    measured = table[table["source"] == "measured"].iloc[0]
    summary = pd.read_csv(sift_run / "summary.csv").iloc[0]
    for column in ("h_acc@1", "h_acc@3", "h_acc@5", "mma@3"):
        assert measured[f"{column}_lo"] == pytest.approx(summary[f"{column}_lo"])
        assert measured[f"{column}_hi"] == pytest.approx(summary[f"{column}_hi"])
    assert "n_pairs_lo" not in table.columns and "outside_ci" not in table.columns
    assert not any(c.startswith("d_") for c in table.columns)
    assert f"{summary['mma@3']:.2f} [{summary['mma@3_lo']:.2f}, {summary['mma@3_hi']:.2f}]" in md_path.read_text()


def test_a_run_written_before_intervals_still_tables(tmp_path):
    """summary.csv without _lo/_hi: recomputed from per_pair.csv when its pairs reproduce the
    summary; absent (the number alone) when they do not or there are none."""
    old = write_run(tmp_path / "old", "hpatches", hpatches_rows([0.5, 2.0, 4.0, 0.7, 9.0, np.inf]), intervals_too=False)
    new = write_run(tmp_path / "new", "hpatches", hpatches_rows([0.5, 2.0, 4.0, 0.7, 9.0, np.inf]))
    assert "h_acc@1_lo" not in pd.read_csv(old / "summary.csv").columns
    old_row = report.paper_table([report.load_run(old)], "hpatches").iloc[0]
    new_row = report.paper_table([report.load_run(new)], "hpatches").iloc[0]
    for column in ("h_acc@1_lo", "h_acc@1_hi", "mma@3_lo", "mma@3_hi"):
        assert old_row[column] == pytest.approx(new_row[column])

    (old / "per_pair.csv").unlink()
    table = report.paper_table([report.load_run(old)], "hpatches")
    assert table[["h_acc@1_lo", "h_acc@1_hi"]].isna().all().all()
    markdown = report.table_to_markdown(table)
    assert "[" not in markdown.splitlines()[2] and f"{table.iloc[0]['h_acc@1']:.2f}" in markdown

    # pairs that do not give the summary's numbers: no interval is claimed for them
    other = write_run(tmp_path / "other", "hpatches", hpatches_rows([0.5] * 6), intervals_too=False)
    hpatches_rows([9.0] * 6).to_csv(other / "per_pair.csv", index=False)
    assert report.paper_table([report.load_run(other)], "hpatches")[["h_acc@1_lo"]].isna().all().all()


def test_the_sample_tables_hold_intervals_that_contain_their_numbers():
    root = Path(__file__).resolve().parents[2] / "results" / "sample"
    for name, columns in (("table1_hpatches", ("h_acc@1", "h_acc@3", "h_acc@5", "mma@3")),
                          ("table2_kitti", ("auc@5", "auc@10", "auc@20", "P")),
                          ("table3_scannet", ("auc@5", "auc@10", "auc@20", "P"))):
        table = pd.read_csv(root / name / "table.csv").query("source == 'measured'")
        assert len(table) == 7
        for column in columns:
            assert (table[f"{column}_lo"] <= table[column] + 1e-9).all() and (table[column] <= table[f"{column}_hi"] + 1e-9).all()


# --------------------------------------------------------------------------- compare


def test_compare_finds_the_run_with_the_smaller_errors(sift_run, tmp_path):
    shifted = tmp_path / "shifted"
    shutil.copytree(sift_run, shifted)
    per_pair = pd.read_csv(shifted / "per_pair.csv")
    assert np.isfinite(per_pair["h_error"]).sum() >= 8
    per_pair["h_error"] = per_pair["h_error"] + 2.0
    per_pair.to_csv(shifted / "per_pair.csv", index=False)

    result = ok("compare", sift_run, shifted, "--out", tmp_path / "cmp")
    table = pd.read_csv(tmp_path / "cmp" / "compare.csv").set_index("metric")
    # h_error: the median, every pair moved by 2 px (the failures stay +inf): exactly +2
    assert table.loc["h_error", "verdict"] == "A better" and table.loc["h_error", "d"] == pytest.approx(2.0)
    assert table.loc["h_error", "d_lo"] == pytest.approx(2.0) and table.loc["h_error", "statistic"] == "median"
    assert table.loc["mma@3", "verdict"] == "no difference detectable"  # mma untouched
    assert set(table.index) == {"mma@3", "h_error", "h_acc@1", "h_acc@3", "h_acc@5"}
    assert (table.loc[["mma@3", "h_acc@1", "h_acc@3", "h_acc@5"], "statistic"] == "mean").all()
    assert (table["n"] == len(per_pair)).all()
    markdown = (tmp_path / "cmp" / "compare.md").read_text()
    assert "A better" in markdown and markdown.count("\n|") >= 6 and "A: sift" in markdown and "B: shifted" in markdown
    assert "compare.csv" in result.output

    # B - A flips with the order
    swapped = compare_runs(report.load_run(shifted), report.load_run(sift_run))
    assert {r.metric: r.verdict for r in swapped.results}["h_error"] == "B better"


def test_compare_of_a_run_with_its_copy_detects_nothing(sift_run, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(sift_run, copy)
    result = ok("compare", sift_run, copy, "--mma", "all")
    comparison = compare_runs(report.load_run(sift_run), report.load_run(copy), mma=parse_mma("all", ["mma@1", "mma@3"]))
    n = len(pd.read_csv(sift_run / "per_pair.csv"))
    assert [r.metric for r in comparison.results][:2] == ["mma@1", "mma@3"]
    for r in comparison.results:
        assert r.verdict == "no difference detectable" and r.n == n and r.diff == 0 and r.p_value == 1
    assert "mma@10" in result.output


def test_compare_pose_runs_on_the_pairs_both_hold(tmp_path):
    rng = np.random.default_rng(0)
    n = 30
    errors = rng.uniform(1.0, 30.0, n)
    frame = pd.DataFrame({"pair": [f"p{k}" for k in range(n)], "n_matches": 500, "err_R": errors, "err_t": errors,
                          "err_pose": errors, "precision@1e-4": rng.uniform(0.5, 0.9, n), "precision@5e-4": 0.95})
    a = write_run(tmp_path / "a", "megadepth", frame)
    better = frame.assign(err_pose=frame["err_pose"] / 3.0, err_R=frame["err_R"] / 3.0).iloc[3:]  # B lacks 3 pairs
    b = write_run(tmp_path / "b", "megadepth", better.reset_index(drop=True), method="dfm")
    comparison = compare_runs(report.load_run(a), report.load_run(b))
    assert (comparison.n_a, comparison.n_b, comparison.n_common) == (30, 27, 27)
    verdicts = {r.metric: r.verdict for r in comparison.results}
    assert list(verdicts) == ["err_pose", "err_pose<5", "err_pose<10", "err_pose<20", "precision@1e-4"]
    assert verdicts["err_pose"] == "B better" and verdicts["err_pose<10"] == "B better"
    assert verdicts["precision@1e-4"] == "no difference detectable"
    assert [r.statistic for r in comparison.results] == ["median", "mean", "mean", "mean", "mean"]


def test_compare_refuses_runs_of_two_benchmarks(sift_run, tmp_path):
    pose = write_run(tmp_path / "pose", "megadepth", pd.DataFrame({
        "pair": ["p0"], "n_matches": [5], "err_R": [1.0], "err_t": [1.0], "err_pose": [1.0],
        "precision@1e-4": [0.5], "precision@5e-4": [0.5]}))
    line = one_line_error(invoke("compare", sift_run, pose))
    assert "hpatches run" in line and "megadepth run" in line and "one benchmark" in line
    assert "--mma" in one_line_error(invoke("compare", sift_run, sift_run, "--mma", "12"))
