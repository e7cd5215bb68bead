"""`compare` whose verdict, interval and p agree;
`compare`, `table` and `check` at 80 columns in a log or a pipe; a run on other pairs than the
paper's said so; `check` against broken baselines and runs whose two CSVs disagree.

Run folders are written here from per-pair rows (summary.csv made from them as a run makes it),
plus one small SIFT run on the shared HPatches sample.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from e3cm_bench.benchmarks import intervals
from e3cm_bench.benchmarks import get_benchmark
from helpers import invoke, one_line_error, sift_hpatches_run, table_lines

WIDTH = 80


def write_run(folder: Path, benchmark: str, per_pair: pd.DataFrame, method: str = "sift") -> Path:
    """A run folder as a run writes it: the summary (with intervals) from the per-pair rows."""
    folder.mkdir(parents=True)
    bench = get_benchmark(benchmark)
    ev = bench.eval_settings()
    rows = per_pair.to_dict("records")
    summary = bench.summarize(rows, ev)
    summary.update(intervals.summary_intervals(bench, rows, ev, summary=summary, n_samples=200))
    config = {"benchmark": benchmark, "method": method, "identity": {"matcher": method, "settings": {}},
              "evaluation": {"seed": 0}}
    (folder / "config.yaml").write_text(yaml.safe_dump(config))
    pd.DataFrame([summary]).to_csv(folder / "summary.csv", index=False)
    per_pair.to_csv(folder / "per_pair.csv", index=False)
    return folder


def homography_rows(rng, n: int, scale: float, fail: float) -> pd.DataFrame:
    h_error = rng.exponential(scale, n)
    h_error[rng.random(n) < fail] = np.inf  # no homography: a failure
    sequences = [("i_a" if k % 2 else "v_b") for k in range(n)]
    mma = np.clip(rng.uniform(0.3, 0.9, n) - 0.05 * scale, 0, 1)
    return pd.DataFrame({"pair": [f"{s}/{k}" for k, s in enumerate(sequences)], "sequence": sequences,
                         "n_matches": rng.integers(5, 900, n), **{f"mma@{t}": mma for t in range(1, 11)},
                         "h_error": h_error})


def pose_rows(rng, n: int, scale: float, fail: float) -> pd.DataFrame:
    err = rng.exponential(scale, n)
    err[rng.random(n) < fail] = np.inf
    return pd.DataFrame({"pair": [f"p{k}" for k in range(n)], "n_matches": rng.integers(5, 900, n), "err_R": err,
                         "err_t": err, "err_pose": err, "precision@1e-4": rng.uniform(0.2, 0.9, n),
                         "precision@5e-4": 0.9})


@pytest.fixture(scope="module")
def sift_run(shared_data: Path, tmp_path_factory) -> Path:
    return sift_hpatches_run(shared_data, tmp_path_factory.mktemp("compare") / "sift", max_side=320, limit=6)


def no_wide_line(text: str) -> None:
    """A pipe's layout (docs/cli.md, Output): a table's line (columns two spaces or more apart, or
    a rule) within 80 columns; a message (a sentence) one line however long; nothing cut."""
    table = table_lines(text)
    wide = [line for line in table if len(line) > WIDTH]
    assert table and not wide, wide
    assert "…" not in text  # nothing cut


@pytest.fixture
def wide(monkeypatch):
    """A wide log (COLUMNS=1000), for tests that read long paths out of the messages."""
    monkeypatch.setenv("COLUMNS", "1000")


@pytest.fixture
def pipe_width(monkeypatch):
    """COLUMNS unset, as in a CI log: the commands lay out for 80 columns."""
    monkeypatch.delenv("COLUMNS", raising=False)


# --------------------------------------------------------------------------- compare: one rule


CASES = [  # benchmark, rows, A's scale and failure rate, B's
    ("hpatches", homography_rows, (1.0, 0.1), (3.0, 0.3)),
    ("hpatches", homography_rows, (2.0, 0.2), (2.0, 0.2)),
    ("hpatches", homography_rows, (0.8, 0.0), (0.8, 0.6)),  # B fails on more than half: its median is +inf
    ("megadepth", pose_rows, (4.0, 0.1), (6.0, 0.1)),
    ("megadepth", pose_rows, (8.0, 0.3), (3.0, 0.0)),
]


@pytest.mark.parametrize("case", range(len(CASES)))
@pytest.mark.parametrize("alpha", [0.05, 0.2])
def test_every_row_of_compare_agrees_with_itself(tmp_path, case, alpha):
    """On every row: the verdict names a winner exactly when the interval excludes 0, exactly when
    p < alpha, on the side the interval says; n is every pair both hold (a failure counts, as
    +inf); A and B are the row's statistic over those pairs, computed here independently."""
    benchmark, make, (scale_a, fail_a), (scale_b, fail_b) = CASES[case]
    rng = np.random.default_rng(case)
    n = int(rng.integers(12, 60))
    a_rows, b_rows = make(rng, n, scale_a, fail_a), make(rng, n, scale_b, fail_b)
    error = "h_error" if benchmark == "hpatches" else "err_pose"
    b_rows.loc[2, error] = np.nan  # an error the run could not compute: a failure too
    a = write_run(tmp_path / "a", benchmark, a_rows)
    b = write_run(tmp_path / "b", benchmark, b_rows.iloc[1:].reset_index(drop=True), method="other")  # B lacks a pair
    result = invoke("compare", a, b, "--out", tmp_path / "cmp", "--alpha", alpha)
    assert result.exit_code == 0, result.output
    table = pd.read_csv(tmp_path / "cmp" / "compare.csv").set_index("metric")
    assert len(table) >= 5
    common_a, common_b = a_rows.iloc[1:], b_rows.iloc[1:]
    errors_a = common_a[error].fillna(np.inf).to_numpy(float)
    errors_b = common_b[error].fillna(np.inf).to_numpy(float)
    for metric, row in table.iterrows():
        excludes = row["d_lo"] > 0 or row["d_hi"] < 0
        assert (row["verdict"] != "no difference detectable") == excludes, (metric, row.to_dict())
        assert (row["p_value"] < alpha) == excludes, (metric, row.to_dict())
        if excludes:
            b_up = row["d_lo"] > 0
            assert row["verdict"] == ("B better" if b_up == (row["better"] == "higher") else "A better")
        assert row["n"] == n - 1, metric  # every common pair, failures included
    assert table.loc[error, "statistic"] == "median"
    assert table.loc[error, "a"] == pytest.approx(np.median(errors_a))
    assert table.loc[error, "b"] == pytest.approx(np.median(errors_b))
    threshold, inclusive = (1, True) if benchmark == "hpatches" else (5, False)
    name = f"h_acc@{threshold}" if benchmark == "hpatches" else f"err_pose<{threshold}"
    passes_b = errors_b <= threshold if inclusive else errors_b < threshold
    assert table.loc[name, "statistic"] == "mean" and table.loc[name, "b"] == pytest.approx(passes_b.mean())


def test_sift_against_a_worse_run_that_fails_pairs_it_solves(sift_run, tmp_path):
    """The reported case: B fails on pairs A solves. Before, h_error's means skipped those pairs
    and the interval held 0 beside 'A better'; now the median counts them and all three agree."""
    worse = tmp_path / "worse"
    shutil.copytree(sift_run, worse)
    per_pair = pd.read_csv(worse / "per_pair.csv")
    per_pair.loc[:3, "h_error"] = np.inf
    per_pair.to_csv(worse / "per_pair.csv", index=False)
    result = invoke("compare", sift_run, worse, "--out", tmp_path / "cmp")
    assert result.exit_code == 0, result.output
    table = pd.read_csv(tmp_path / "cmp" / "compare.csv").set_index("metric")
    row = table.loc["h_error"]
    assert row["n"] == len(per_pair) and row["b"] == np.inf and row["d"] == np.inf  # the failures count
    # 6 pairs: a resample can miss the failures, so the interval reaches 0 and no winner is named
    assert row["d_lo"] == 0 and row["verdict"] == "no difference detectable" and row["p_value"] >= 0.05
    # 4 of 6 pairs lost under 3 px: the interval of the accuracy excludes 0, and the verdict says so
    row = table.loc["h_acc@3"]
    assert row["d_hi"] < 0 and row["verdict"] == "A better" and row["p_value"] < 0.05


# --------------------------------------------------------------------------- 80 columns


def test_compare_fits_80_columns_without_cutting_a_name(tmp_path, pipe_width):
    rng = np.random.default_rng(7)
    a = write_run(tmp_path / "a", "megadepth", pose_rows(rng, 1200, 4.0, 0.1), method="a-method-with-a-long-label-x")
    b = write_run(tmp_path / "b", "megadepth", pose_rows(rng, 1200, 6.0, 0.1), method="another-long-label-y-z")
    result = invoke("compare", a, b)
    assert result.exit_code == 0, result.output
    no_wide_line(result.output)
    for name in ("err_pose", "err_pose<5", "err_pose<10", "err_pose<20", "precision@1e-4",
                 "a-method-with-a-long-label-x", "another-long-label-y-z"):
        assert name in result.output, name
    # one table row per metric, each on one line, with its verdict
    rows = [line for line in result.output.splitlines() if line.startswith(("err_pose", "precision"))]
    assert len(rows) == 5 and all(line.rstrip().endswith(("better", "detectable")) for line in rows), rows


def test_table_fits_80_columns_and_says_the_pairs_differ_from_the_papers(sift_run, tmp_path, pipe_width):
    """The paper-layout table on a 6-pair run, read at 80 columns; its differences
    from the paper's SIFT+NN are marked 'other pairs' with a note saying which pairs each side
    holds, never 'outside CI' (which reads as a regression)."""
    result = invoke("table", sift_run, "--out", tmp_path / "t" / "table")
    assert result.exit_code == 0, result.output
    no_wide_line(result.output)
    text = " ".join(result.output.split())
    assert "outside" not in result.output and "(other pairs)" in result.output
    assert "sift is measured on 6 pairs, SIFT+NN in the paper on the full HPatches sequences" in text
    assert "neither a regression nor an improvement" in text
    for name in ("h_acc@1", "h_acc@3", "h_acc@5", "mma@3", "d_h_acc@1", "SuperPoint+SuperGlue"):
        assert name in result.output, name
    table = pd.read_csv(tmp_path / "t" / "table.csv")
    measured = table[table["source"] == "measured"].iloc[0]
    assert measured["other_pairs"].startswith("6 pairs; the paper: the full HPatches")
    assert pd.isna(measured["outside_ci"])  # no interval test against another pair set
    markdown = (tmp_path / "t" / "table.md").read_text()
    assert "(other pairs)" in markdown and "Note: sift is measured on 6 pairs" in markdown


def test_the_report_page_says_the_pairs_differ_from_the_papers(sift_run, tmp_path):
    result = invoke("report", sift_run, "--out", tmp_path / "site")
    assert result.exit_code == 0, result.output
    page = (tmp_path / "site" / "index.html").read_text()
    assert "(other pairs)" in page and "sift is measured on 6 pairs" in page and "outside 95% CI" not in page


def test_commands_in_a_pipe_write_no_line_over_80_columns(sift_run, tmp_path):
    """stdout a pipe (as in CI), COLUMNS unset, stdin and stderr not terminals either: compare,
    table and check in one interpreter (one start-up), each line at most 80 columns."""
    worse = tmp_path / "worse"
    shutil.copytree(sift_run, worse)
    per_pair = pd.read_csv(worse / "per_pair.csv")
    per_pair["h_error"] = per_pair["h_error"] * 3
    per_pair.to_csv(worse / "per_pair.csv", index=False)
    baseline = tmp_path / "bl" / "base.csv"
    assert invoke("check", sift_run, "--baseline", baseline, "--update").exit_code == 0
    script = (
        "import sys\nfrom e3cm_bench.cli import app\n"
        "for args in sys.argv[1:]:\n"
        "    try:\n        app(args.split('|'), standalone_mode=False)\n"
        "    except SystemExit:\n        pass\n"
    )
    commands = [f"compare|{sift_run}|{worse}", f"table|{sift_run}|--out|{tmp_path / 't' / 'table'}",
                f"check|{sift_run}|--baseline|{baseline}|--tolerance|h_acc@1=0"]
    env = {k: v for k, v in os.environ.items() if k != "COLUMNS"}
    done = subprocess.run([sys.executable, "-c", script, *commands], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                          stdin=subprocess.DEVNULL, env=env, text=True, timeout=300)
    print(done.stdout, done.stderr)
    assert "Traceback" not in done.stderr
    text = " ".join(done.stdout.split())
    assert "A better" in text and "SuperPoint+SuperGlue" in text and "(other pairs)" in text and "no regression" in text
    no_wide_line(done.stdout)


def test_check_writes_each_message_on_one_line_in_a_pipe(sift_run, tmp_path, pipe_width):
    baseline = tmp_path / "base.csv"
    assert invoke("check", sift_run, "--baseline", baseline, "--update").exit_code == 0
    table = pd.read_csv(baseline)
    table["mma@3"] = table["mma@3"] + 0.2  # the run now falls far below it
    table.to_csv(baseline, index=False)
    result = invoke("check", sift_run, "--baseline", baseline)
    assert result.exit_code == 1
    assert "…" not in result.output
    lines = result.output.splitlines()
    # each message whole on its line, the paths in it unbroken (issue 70: a log never breaks a sentence)
    assert any(line.startswith("regression: sift on hpatches: mma@3") and "(tolerance" in line for line in lines)
    assert any(line.startswith("problem: ") and str(baseline) in line and line.endswith("check --update)")
               for line in lines), result.output


# --------------------------------------------------------------------------- check against broken baselines


@pytest.fixture
def baseline(sift_run, tmp_path) -> Path:
    path = tmp_path / "bl" / "base.csv"
    result = invoke("check", sift_run, "--baseline", path, "--update")
    assert result.exit_code == 0, result.output
    assert path.with_name("base.pairs.csv").is_file()
    # the baseline as written checks clean: the run's two CSVs and the baseline's two files agree
    result = invoke("check", sift_run, "--baseline", path)
    assert result.exit_code == 0 and "check: no regression" in result.output, result.output
    return path


@pytest.mark.parametrize("value", ["-inf", "inf", "+Infinity"])
def test_an_infinite_baseline_value_is_refused(sift_run, baseline, value):
    table = pd.read_csv(baseline, dtype=str)
    table.loc[0, "mma@3"] = value
    table.to_csv(baseline, index=False)
    line = one_line_error(invoke("check", sift_run, "--baseline", baseline))
    assert str(baseline) in line and "column mma@3" in line and "not a finite number" in line
    assert f"{float(value)}" in line


@pytest.mark.parametrize("breakage", ["dev_null", "garbage", "no_keys", "empty_rows"])
def test_a_per_pair_baseline_that_cannot_be_used_is_refused(sift_run, baseline, breakage):
    pairs = baseline.with_name("base.pairs.csv")
    pairs.unlink()
    if breakage == "dev_null":
        pairs.symlink_to(os.devnull)
    elif breakage == "garbage":
        pairs.write_bytes(b'\x00\xff"unterminated\n"a,b\n')
    elif breakage == "no_keys":
        pairs.write_text("x,y\n1,2\n")
    else:
        pairs.write_text("benchmark,method,pair,mma@3\n")
    line = one_line_error(invoke("check", sift_run, "--baseline", baseline))
    assert str(pairs) in line


def test_a_run_whose_per_pair_and_summary_disagree_fails_the_check(sift_run, baseline, tmp_path, wide):
    edited = tmp_path / "edited" / "sift"
    shutil.copytree(sift_run, edited)
    per_pair = pd.read_csv(edited / "per_pair.csv")
    per_pair["mma@3"] = per_pair["mma@3"] * 0.5
    per_pair.to_csv(edited / "per_pair.csv", index=False)
    result = invoke("check", edited, "--baseline", baseline)
    assert result.exit_code == 1, result.output
    text = " ".join(result.output.split())
    assert f"problem: {edited / 'per_pair.csv'} and {edited / 'summary.csv'} disagree: mma@3" in text
    assert "no regression" not in text


def test_a_per_pair_baseline_that_disagrees_with_its_aggregate_fails_the_check(sift_run, baseline, wide):
    pairs = baseline.with_name("base.pairs.csv")
    table = pd.read_csv(pairs)
    table.loc[0, "h_error"] = 1e6  # that pair no longer passes h_acc@1..5
    table.to_csv(pairs, index=False)
    result = invoke("check", sift_run, "--baseline", baseline)
    assert result.exit_code == 1, result.output
    text = " ".join(result.output.split())
    assert f"{pairs} and {baseline} disagree on sift on hpatches: h_acc@1" in text and "no regression" not in text
