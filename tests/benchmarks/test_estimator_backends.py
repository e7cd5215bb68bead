"""The evaluation's robust estimators as backends behind one loader (estimators.load_estimator),
and the benchmarks naming the two-view geometry their evaluation estimates, which export stores
(Benchmark.two_view_geometry) instead of choosing an estimator itself."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from e3cm_bench.geometry import estimators
from e3cm_bench.benchmarks import EvalSettings, get_benchmark
from e3cm_bench.benchmarks.pose import PoseBenchmark
from e3cm_bench.datasets.base import Pair
from e3cm_bench.geometry.two_view import warp_points
from e3cm_bench.ground.matches import Matches


def plane_matches(n: int = 200, outliers: int = 40, seed: int = 3):
    """Matches under a known homography, the last `outliers` of them moved far off it."""
    rng = np.random.default_rng(seed)
    H = np.array([[0.9, 0.05, 20.0], [-0.04, 1.1, 10.0], [1e-4, 5e-5, 1.0]])
    x0 = rng.uniform(0, 500, (n, 2))
    x1 = warp_points(H, x0)
    x1[n - outliers:] += rng.uniform(30, 80, (outliers, 2))
    return H, x0, x1


def test_the_loader_gives_each_backend_once_and_refuses_an_unknown_one():
    assert estimators.ESTIMATORS == ("opencv", "poselib")
    backend = estimators.load_estimator("opencv")
    assert isinstance(backend, estimators.OpenCVEstimator) and estimators.load_estimator("opencv") is backend
    with pytest.raises(ValueError, match="unknown estimator 'magic'; choose one of opencv, poselib"):
        estimators.load_estimator("magic")


def test_the_functions_are_the_backends_estimates():
    _, x0, x1 = plane_matches()
    opencv = estimators.load_estimator("opencv")
    assert np.array_equal(estimators.homography(x0, x1, 3.0, 2000, 0.999, seed=2), opencv.homography(x0, x1, 3.0, 2000, 0.999, 2))
    assert np.array_equal(estimators.fundamental(x0, x1, 1.0, 2000, 0.999, seed=0),
                          opencv.fundamental(x0, x1, 1.0, 2000, 0.999, 0))


def test_homography_geometry_holds_the_estimate_and_the_matches_within_the_threshold():
    H, x0, x1 = plane_matches()
    found = estimators.homography_geometry(x0, x1, 3.0, 2000, 0.999)
    assert np.allclose(found["H"] / found["H"][2, 2], H, atol=1e-6)
    assert found["inliers"].tolist() == [True] * 160 + [False] * 40
    assert estimators.homography_geometry(x0[:3], x1[:3], 3.0, 2000, 0.999) is None  # too few: no estimate


class FixedH:
    """A backend of our own: every homography is the identity (to see who asks the loader)."""

    name = "fixed"

    def homography(self, x0, x1, threshold_px, max_iters, confidence, seed=0, method="ransac"):
        return np.eye(3)


def test_a_benchmark_evaluates_through_the_backend_its_settings_name(monkeypatch, tmp_path):
    monkeypatch.setitem(estimators.BACKENDS, "fixed", FixedH)
    monkeypatch.setattr(estimators, "_loaded", {})
    _, x0, x1 = plane_matches()
    matches = Matches(x0, x1, None, info={"size0": (500, 500), "size1": (500, 500)})
    pair = Pair("p", tmp_path / "a.png", tmp_path / "b.png", H=np.diag([2.0, 2.0, 1.0]))
    evd = get_benchmark("evd")
    ev = EvalSettings(estimator="fixed")
    assert evd.evaluate_pair(pair, matches, ev)["h_found"] == 1
    assert np.array_equal(evd.two_view_geometry(pair, matches, ev)["H"], np.eye(3))


def test_export_stores_the_geometry_each_benchmark_evaluates_with(tmp_path):
    H, x0, x1 = plane_matches()
    matches = Matches(x0, x1, None, info={"size0": (500, 500), "size1": (500, 500)})
    pair = Pair("p", tmp_path / "a.png", tmp_path / "b.png", H=H)
    hpatches, evd, wxbs = (get_benchmark(name) for name in ("hpatches", "evd", "wxbs"))
    ev = EvalSettings()
    assert hpatches.two_view_geometry(pair, matches, ev)["inliers"].sum() == 160
    # EVD's evaluation estimates with its protocol's MAGSAC++ at 0.5 px: that estimate is the one stored
    ev_evd = evd.resolve_eval()
    assert ev_evd.opencv_method == "magsac"
    assert np.array_equal(evd.two_view_geometry(pair, matches, ev_evd)["H"], evd.estimate(matches, ev_evd))
    assert wxbs.two_view_geometry(pair, matches, wxbs.resolve_eval()) is None  # F: nothing COLMAP's export holds


def test_the_pose_geometry_is_the_pose_benchmarks_estimate():
    rng = np.random.default_rng(0)
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    points = np.column_stack([rng.uniform(-2, 2, 150), rng.uniform(-1.5, 1.5, 150), rng.uniform(4, 8, 150)])
    angle = np.deg2rad(5)
    R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    t = np.array([1.0, 0.0, 0.1])
    project = lambda X: (X @ K.T)[:, :2] / X[:, 2:]  # noqa: E731
    x0, x1 = project(points), project(points @ R.T + t)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    pair = Pair("p", Path("a.png"), Path("b.png"), K0=K, K1=K, T_0to1=T)
    matches = Matches(x0, x1, None)
    found = PoseBenchmark.two_view_geometry(pair, matches, EvalSettings())
    assert np.allclose(found["R"], R, atol=1e-4) and found["inliers"].all()
    assert np.allclose(found["t"] / np.linalg.norm(found["t"]), t / np.linalg.norm(t), atol=1e-3)
