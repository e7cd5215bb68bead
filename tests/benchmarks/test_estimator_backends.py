"""The evaluation's robust estimators as backends behind one loader (estimators.load_estimator),
and the benchmarks naming the two-view geometry their evaluation estimates, which export stores
(Benchmark.two_view_geometry) instead of choosing an estimator itself."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from e3cm_bench.geometry import estimators, metrics
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
    assert estimators.ESTIMATORS == ("opencv", "poselib", "pycolmap")
    backend = estimators.load_estimator("opencv")
    assert isinstance(backend, estimators.OpenCVEstimator) and estimators.load_estimator("opencv") is backend
    with pytest.raises(ValueError, match="unknown estimator 'magic'; choose one of opencv, poselib, pycolmap"):
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


def _two_views(seed: int = 0):
    rng = np.random.default_rng(seed)
    points = rng.uniform([-2, -2, 4], [2, 2, 8], (300, 3))
    K = np.array([[700.0, 0, 320], [0, 700.0, 240], [0, 0, 1]])
    R = cv2.Rodrigues(np.array([0.02, 0.1, -0.03]))[0]
    t = np.array([1.0, 0.1, 0.05])

    def project(X, R, t):
        x = (K @ (X @ R.T + t).T).T
        return x[:, :2] / x[:, 2:]

    x0, x1 = project(points, np.eye(3), np.zeros(3)), project(points, R, t)
    x1[:60] += rng.uniform(-50, 50, (60, 2))  # outliers
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return x0, x1, K, T


@pytest.mark.parametrize("estimator, method", [("opencv", "ransac"), ("opencv", "magsac"), ("opencv", "accurate"),
                                               ("poselib", "ransac"), ("pycolmap", "ransac")])
def test_every_pose_estimator_of_the_sweep_recovers_a_pose(estimator, method):
    """The sweep's estimators (issue 69): OpenCV's three robust methods, PoseLib and pycolmap."""
    pytest.importorskip("poselib" if estimator == "poselib" else "cv2")
    if estimator == "pycolmap":
        pytest.importorskip("pycolmap")
    from e3cm_bench.geometry.metrics import pose_error

    x0, x1, K, T = _two_views()
    found = estimators.relative_pose(x0, x1, K, K, estimators.PoseRansac(1.0, 0.99999, estimator, 0, method),
                                     sizes=((640, 480), (640, 480)))
    err_R, err_t = pose_error(T, found[0], found[1])
    assert err_R < 0.2 and err_t < 0.5 and found[2][60:].mean() > 0.95 and found[2][:60].mean() < 0.1


def test_pycolmap_estimates_h_and_f():
    pytest.importorskip("pycolmap")
    H, x0, x1 = plane_matches()
    backend = estimators.load_estimator("pycolmap")
    assert metrics.homography_corner_error(backend.homography(x0, x1, 3.0, 2000, 0.999, 0), H, 640, 480) < 1e-2
    x0, x1, _, _ = _two_views()
    F = backend.fundamental(x0, x1, 1.0, 2000, 0.999, 0)
    residual = np.abs(np.sum(np.column_stack([x1, np.ones(len(x1))]) @ F * np.column_stack([x0, np.ones(len(x0))]), axis=1))
    assert np.median(residual[60:]) < np.median(residual[:60])
