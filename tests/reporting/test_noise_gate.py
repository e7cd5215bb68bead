"""The regression gate's noise model: perturbations (perturb.py), the ensemble and its
statistics (ensemble.py, stats/noise.py, noise_gate.py), `check` with it, `--repeats`, and the
committed demo baselines against another CPU's runs and against degraded runs."""

from __future__ import annotations

import itertools
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from e3cm_bench.geometry import estimators, two_view as geometry
from e3cm_bench.stats.perturb import Perturbation, perturb_correspondences, perturb_map, perturbed
from e3cm_bench.stats.noise import PairMove, count_gate, member_picks, metric_alpha, resampled_gate
from helpers import flat, invoke, one_line_error

REPO_ROOT = Path(__file__).resolve().parents[2]
BASELINES = REPO_ROOT / "results" / "baselines"
AMD_RUNS = REPO_ROOT.parent / "shared" / "cpu-runs" / "amd-epyc-avx512-demo"


# --------------------------------------------------------------------------- perturbations


def test_perturbations_are_the_identity_outside_a_draw_and_seeded_inside():
    x = torch.randn(1, 16, 6, 7).contiguous(memory_format=torch.channels_last)
    a, b = np.random.default_rng(0).uniform(0, 500, (2, 40, 2))
    assert perturb_map(x) is x
    assert perturb_correspondences(a, b)[2] is None
    with perturbed(Perturbation(draw=3)):
        y, again = perturb_map(x), perturb_map(x)
        a3, b3, order = perturb_correspondences(a, b)
        with pytest.raises(RuntimeError):
            with perturbed(Perturbation(draw=4)):
                pass
    with perturbed(Perturbation(draw=4)):
        other = perturb_map(x)
    assert torch.equal(y, again) and not torch.equal(y, other)  # seeded by the draw and the bytes
    relative = float((y - x).norm() / x.norm())
    assert 0.5e-5 < relative < 2e-5  # the parity scale: 1e-5 of the map's RMS
    assert y.is_contiguous(memory_format=torch.channels_last)
    assert sorted(order) == list(range(40))
    assert np.all(np.abs(a3 - a[order]) <= np.finfo(np.float32).eps * np.abs(a[order]) + 1e-12)
    assert not np.array_equal(a3, a[order])


def test_a_perturbed_pose_keeps_its_inliers_aligned_with_the_input():
    rng = np.random.default_rng(1)
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    X = np.c_[rng.uniform(-2, 2, (200, 2)), rng.uniform(4, 8, 200)]
    t = np.array([0.5, 0.0, 0.05])
    x0 = (X @ K.T)[:, :2] / X[:, 2:]
    X1 = X + t
    x1 = (X1 @ K.T)[:, :2] / X1[:, 2:]
    x1[150:] = rng.uniform(0, 640, (50, 2))  # outliers at the end
    with perturbed(Perturbation(draw=1)):
        _, _, inliers = geometry.estimate_relative_pose(x0, x1, K, K, 1.0, 0.9999)
    assert inliers[:150].mean() > 0.9 and inliers[150:].mean() < 0.2


def test_a_seed_acts_on_opencvs_ransac_through_the_order():
    rng = np.random.default_rng(0)
    x0 = rng.uniform(0, 600, (300, 2))
    H = np.array([[1.1, 0.05, 10], [0.02, 0.95, -5], [1e-4, 2e-5, 1]])
    x1 = geometry.warp_points(H, x0) + rng.normal(0, 1.5, (300, 2))
    x1[200:] = rng.uniform(0, 600, (100, 2))
    plain = geometry.estimate_homography(x0, x1, 3.0, 5000, 0.9999)
    assert np.array_equal(estimators.homography(x0, x1, 3.0, 5000, 0.9999, seed=0), plain)  # seed 0: as before
    seeded = [estimators.homography(x0, x1, 3.0, 5000, 0.9999, seed=s) for s in (1, 2, 3)]
    assert any(not np.allclose(h, plain) for h in seeded)
    assert np.array_equal(seeded[0], estimators.homography(x0, x1, 3.0, 5000, 0.9999, seed=1))


# --------------------------------------------------------------------------- statistics


def test_count_gate_matches_enumeration():
    rng = np.random.default_rng(2)
    p = rng.uniform(0, 1, 7)
    members = [np.array([True] * int(round(q * 20)) + [False] * (20 - int(round(q * 20)))) for q in p]
    share = np.array([(m.sum() + 0.5) / (len(m) + 1) for m in members])  # the predictive share
    counts = {k: 0.0 for k in range(8)}
    for outcome in itertools.product((0, 1), repeat=7):
        counts[sum(outcome)] += float(np.prod(np.where(outcome, share, 1 - share)))
    for observed in range(8):
        gate = count_gate("h_acc@1", members, observed / 7, 0.5, alpha=0.05)
        below = sum(v for k, v in counts.items() if k <= observed)
        above = sum(v for k, v in counts.items() if k >= observed)
        assert gate.p_value == pytest.approx(min(1.0, 2 * min(below, above)), abs=1e-12)
    always = [np.ones(200, bool)] * 15
    assert count_gate("h_acc@1", always, 12 / 15, 1.0, 0.01).status == "regression"
    assert count_gate("h_acc@1", always, 14 / 15, 1.0, 0.01).status == "ok"  # one new flip: the prior allows it
    assert count_gate("h_acc@1", always, 1.0, 1.0, 0.01).status == "ok"


def test_resampled_gate_and_pair_moves():
    samples = np.random.default_rng(3).normal(0.9, 0.01, 4000)
    assert resampled_gate("mma@3", samples, 0.905, 0.9, 0.001, draws=20).status == "ok"
    assert resampled_gate("mma@3", samples, 0.85, 0.9, 0.001, draws=20).status == "regression"
    assert resampled_gate("mma@3", samples, 0.95, 0.9, 0.001, draws=20).status == "improvement"
    constant = np.full(100, 0.5)
    assert resampled_gate("P", constant, 0.5, 0.5, 0.01, draws=20).status == "ok"
    assert resampled_gate("P", constant, 0.49, 0.5, 0.01, draws=20).status == "regression"
    picks = member_picks([1, 3, 5], 2000, seed=0)
    assert picks.shape == (2000, 3) and (picks[:, 0] == 0).all() and set(picks[:, 2]) == set(range(5))
    assert PairMove("p", "h_error", 1.0, 1.2, 0.8, 1.3).inside
    assert not PairMove("p", "h_error", 1.0, 1.4, 0.8, 1.3).inside
    assert PairMove("p", "h_error", 1.0, np.inf, 0.8, np.inf).inside
    assert not PairMove("p", "h_error", 1.0, np.inf, 0.8, 1.3).inside
    assert metric_alpha(50, 0.01) == pytest.approx(2e-4)


# --------------------------------------------------------------------------- check with an ensemble


@pytest.fixture(scope="module")
def sift_demo(tmp_path_factory) -> Path:
    """The full demo's HPatches-format sequences, SIFT only (the committed baselines' pairs)."""
    out = tmp_path_factory.mktemp("gate") / "e3cm-demo"
    result = invoke("demo", "--out", out, "--methods", "sift")
    assert result.exit_code == 0, result.output
    return out


def sift_baseline(tmp_path: Path, set_name: str) -> Path:
    """The committed baseline of a demo set (aggregate, per-pair and noise files), SIFT's rows only."""
    stem = f"demo_{set_name}"
    for suffix in (".csv", ".pairs.csv", ".noise.csv"):
        table = pd.read_csv(BASELINES / f"{stem}{suffix}")
        table[table["method"] == "sift"].to_csv(tmp_path / f"{stem}{suffix}", index=False)
    return tmp_path / f"{stem}.csv"


def test_update_with_an_ensemble_then_check_gates_with_it(sift_demo, tmp_path):
    runs = tmp_path / "runs"
    shutil.copytree(sift_demo / "scenes", runs)
    baseline = tmp_path / "base.csv"
    result = invoke("check", runs, "--baseline", baseline, "--update", "--ensemble", "2",
                    "--ensemble-dir", tmp_path / "work")
    assert result.exit_code == 0, result.output
    noise = pd.read_csv(tmp_path / "base.noise.csv")
    pairs = pd.read_csv(tmp_path / "base.pairs.csv")
    assert sorted(noise["draw"].unique()) == [1, 2] and len(noise) == 2 * len(pairs) == 12
    assert "identity" in pd.read_csv(baseline).columns
    result = invoke("check", runs, "--baseline", baseline)
    assert result.exit_code == 0 and "noise model:" in flat(result.output), result.output
    # Rewritten without --ensemble, the stale draws go: check falls back to its tolerances.
    result = invoke("check", runs, "--baseline", baseline, "--update")
    assert result.exit_code == 0 and not (tmp_path / "base.noise.csv").exists()


def test_a_baseline_with_a_repeated_row_is_refused(sift_demo, tmp_path):
    runs = tmp_path / "runs"
    shutil.copytree(sift_demo / "hpatches", runs)
    baseline = tmp_path / "base.csv"
    assert invoke("check", runs, "--baseline", baseline, "--update").exit_code == 0
    table = pd.read_csv(baseline)
    degraded = table.copy()
    degraded["mma@3"] = 0.3
    pd.concat([table, degraded]).to_csv(baseline, index=False)
    line = one_line_error(invoke("check", runs, "--baseline", baseline))
    assert "more than one row" in line and "base.csv" in line


def _shift_keypoints(run: Path, by: float) -> None:
    from e3cm_bench.storage.cache import MatchCache
    from e3cm_bench.ground.matches import Matches

    cache = MatchCache(run / "matches.h5")
    for name in cache.names():
        m = cache.read(name)
        cache.write(name, Matches(m.keypoints0, m.keypoints1 + np.float32([by, 0.0]), m.scores), attrs=m.info)


@pytest.mark.parametrize("set_name, benchmark", [("hpatches", "hpatches"), ("scenes", "yfcc")])
def test_committed_baseline_passes_this_machine_and_fails_shifted_keypoints(sift_demo, tmp_path, set_name, benchmark):
    """SIFT on this machine lies within the committed noise model; the same run with every
    keypoint of image 1 moved by 1 px (re-evaluated, not rematched) is a regression."""
    baseline = sift_baseline(tmp_path, set_name)
    run = tmp_path / "runs" / "sift"
    shutil.copytree(sift_demo / set_name / "sift", run)
    result = invoke("check", run, "--baseline", baseline)
    assert result.exit_code == 0, result.output
    _shift_keypoints(run, 1.0)
    data = sift_demo / "data" / ("hpatches" if set_name == "hpatches" else "scenes")
    extra = ["--pairs", data / "pairs_with_gt.txt"] if set_name == "scenes" else []
    result = invoke(benchmark, "--out", run, "--root", data, "--matcher", "sift", "--eval-only", *extra)
    assert result.exit_code == 0, result.output
    result = invoke("check", run, "--baseline", baseline)
    assert result.exit_code == 1 and "regression: sift on" in flat(result.output), result.output


def _committed_runs(tmp_path: Path, set_name: str, per_pair_of=None) -> Path:
    """Run folders rebuilt from the committed per-pair baseline: each method's pairs as its
    per_pair.csv and their summary; per_pair_of(method, table) may change a method's pairs."""
    from e3cm_bench.benchmarks import EvalSettings, get_benchmark

    pairs = pd.read_csv(BASELINES / f"demo_{set_name}.pairs.csv")
    runs = tmp_path / set_name
    for (bench, method), table in pairs.groupby(["benchmark", "method"]):
        table = table.drop(columns=["benchmark", "method"]).reset_index(drop=True)
        if per_pair_of is not None:
            table = per_pair_of(method, table)
        run = runs / method
        run.mkdir(parents=True)
        (run / "config.yaml").write_text(f"benchmark: {bench}\nmethod: {method}\nidentity: {{matcher: {method}}}\n")
        table.to_csv(run / "per_pair.csv", index=False)
        benchmark = get_benchmark(bench)
        summary = benchmark.summarize(table.to_dict("records"), EvalSettings())
        pd.DataFrame([summary]).to_csv(run / "summary.csv", index=False)
    return runs


@pytest.mark.parametrize("set_name", ["hpatches", "scenes"])
def test_committed_baselines_pass_their_own_pairs(tmp_path, set_name):
    runs = _committed_runs(tmp_path, set_name)
    result = invoke("check", runs, "--baseline", BASELINES / f"demo_{set_name}.csv")
    assert result.exit_code == 0 and "noise model:" in flat(result.output), result.output


@pytest.mark.parametrize("set_name, method, worse", [
    ("hpatches", "e3cm-plus", "e3cm-release"),
    ("hpatches", "sift", "direct"),
    ("scenes", "e3cm-ransac", "e3cm-release"),
])
def test_committed_baselines_fail_a_method_that_became_a_worse_one(tmp_path, set_name, method, worse):
    pairs = pd.read_csv(BASELINES / f"demo_{set_name}.pairs.csv")
    replacement = pairs[pairs["method"] == worse].drop(columns=["benchmark", "method"]).reset_index(drop=True)
    runs = _committed_runs(tmp_path, set_name, lambda m, t: replacement.copy() if m == method else t)
    result = invoke("check", runs, "--baseline", BASELINES / f"demo_{set_name}.csv")
    assert result.exit_code == 1 and f"regression: {method} on" in flat(result.output), result.output


@pytest.mark.parametrize("method", ["sift", "e3cm-plus", "dfm", "e3cm"])
def test_committed_baseline_fails_two_pairs_turned_into_failures(tmp_path, method):
    def fail_two(m: str, table: pd.DataFrame) -> pd.DataFrame:
        if m != method:
            return table
        table = table.copy()
        best = table["h_error"].nsmallest(2).index
        table.loc[best, "h_error"] = np.inf
        table.loc[best, "n_matches"] = 0
        table.loc[best, [c for c in table.columns if c.startswith("mma@")]] = 0.0
        return table

    runs = _committed_runs(tmp_path, "hpatches", fail_two)
    result = invoke("check", runs, "--baseline", BASELINES / "demo_hpatches.csv")
    assert result.exit_code == 1 and f"regression: {method} on hpatches" in flat(result.output), result.output


@pytest.mark.skipif(not AMD_RUNS.is_dir(), reason=f"{AMD_RUNS} not found (the ../shared checkout is absent)")
@pytest.mark.parametrize("set_name", ["hpatches", "scenes"])
def test_the_amd_runs_fall_within_the_committed_model(set_name):
    """../shared/cpu-runs: the demo as run on an AMD EPYC (AVX-512, no AMX): no metric flagged."""
    result = invoke("check", AMD_RUNS / set_name, "--baseline", BASELINES / f"demo_{set_name}.csv")
    assert result.exit_code == 0, result.output


# --------------------------------------------------------------------------- --repeats


def test_repeats_report_the_mean_and_spread_of_seeded_evaluations(sift_demo, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(sift_demo / "hpatches" / "sift", run)
    data = sift_demo / "data" / "hpatches"
    singles = []
    for seed in (0, 1, 2):
        result = invoke("hpatches", "--out", run, "--root", data, "--matcher", "sift", "--eval-only", "--seed", str(seed))
        assert result.exit_code == 0, result.output
        singles.append(pd.read_csv(run / "summary.csv").iloc[0])
    result = invoke("hpatches", "--out", run, "--root", data, "--matcher", "sift", "--eval-only", "--repeats", "3")
    assert result.exit_code == 0, result.output
    summary = pd.read_csv(run / "summary.csv").iloc[0]
    assert summary["repeats"] == 3
    errors = [float(s["h_acc@1"]) for s in singles]
    assert summary["h_acc@1"] == pytest.approx(np.mean(errors))
    assert summary["h_acc@1_sd"] == pytest.approx(np.std(errors, ddof=1))
    assert summary["h_acc@1_lo"] <= summary["h_acc@1"] <= summary["h_acc@1_hi"]
    per_pair = pd.read_csv(run / "per_pair.csv")
    assert len(per_pair) == 15
    line = one_line_error(invoke("hpatches", "--out", run, "--root", data, "--matcher", "sift", "--eval-only",
                                 "--repeats", "0"))
    assert "--repeats" in line


@pytest.mark.parametrize("method", ["dfm", "e3cm", "sift"])
def test_compare_two_ensemble_draws_of_one_run_finds_no_difference(tmp_path, method):
    """Two noise draws of one committed run are the same method on the same pairs: every metric
    of `compare` says no difference is detectable."""
    noise = pd.read_csv(BASELINES / "demo_hpatches.noise.csv")
    folders = []
    for draw in (1, 2):
        def as_draw(m: str, table: pd.DataFrame, draw=draw) -> pd.DataFrame:
            own = noise[(noise["method"] == m) & (noise["draw"] == draw)].drop(columns=["benchmark", "method", "draw"])
            return own.set_index("pair").loc[table["pair"]].reset_index()

        folders.append(_committed_runs(tmp_path / f"draw{draw}", "hpatches", as_draw) / method)
    result = invoke("compare", *folders, "--out", tmp_path / "cmp")
    assert result.exit_code == 0, result.output
    verdicts = pd.read_csv(tmp_path / "cmp" / "compare.csv")["verdict"]
    assert len(verdicts) == 5 and (verdicts == "no difference detectable").all(), list(verdicts)
