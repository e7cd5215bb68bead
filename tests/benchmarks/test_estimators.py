"""The evaluation's robust estimators: OpenCV and PoseLib behind one function each,
chosen by an evaluation setting that --eval-only may change and config.yaml records."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from e3cm_bench.geometry import metrics
from e3cm_bench.benchmarks import EvalSettings
from e3cm_bench.geometry.estimators import PoseRansac, homography, relative_pose
from helpers import invoke, one_line_error, rotation

pytest.importorskip("poselib", reason="PoseLib (the poselib extra) is not installed")


def exact_pair(seed: int = 0):
    """Points of a random scene seen by two cameras: exact pixel correspondences, K, R, t."""
    rng = np.random.default_rng(seed)
    K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
    X = np.column_stack([rng.uniform(-2, 2, 300), rng.uniform(-1.5, 1.5, 300), rng.uniform(4, 9, 300)])
    R = rotation("y", 8.0) @ rotation("x", -3.0)
    t = np.array([0.8, 0.1, 0.2])

    def project(points):
        p = points @ K.T
        return p[:, :2] / p[:, 2:]

    return project(X), project(X @ R.T + t), K, R, t / np.linalg.norm(t)


@pytest.mark.parametrize("estimator", ["opencv", "poselib"])
def test_both_estimators_recover_the_exact_pose(estimator):
    x0, x1, K, R, t = exact_pair()
    R_est, t_est, inliers = relative_pose(x0, x1, K, K, PoseRansac(0.5, 0.99999, estimator, seed=0),
                                         sizes=((640, 480), (640, 480)))
    err_R, err_t = metrics.pose_error(np.vstack([np.column_stack([R, t]), [0, 0, 0, 1]]), R_est, t_est)
    assert err_R < 1e-3 and err_t < 1e-3, (estimator, err_R, err_t)
    assert inliers.sum() == len(x0)


@pytest.mark.parametrize("estimator", ["opencv", "poselib"])
def test_both_estimators_recover_an_exact_homography(estimator):
    rng = np.random.default_rng(1)
    H = np.array([[0.9, 0.05, 12.0], [-0.04, 1.1, -7.0], [1e-4, -5e-5, 1.0]])
    x0 = rng.uniform(0, 640, (200, 2))
    p = np.column_stack([x0, np.ones(200)]) @ H.T
    x1 = p[:, :2] / p[:, 2:]
    x1[:40] += rng.uniform(30, 60, (40, 2))  # outliers
    H_est = homography(x0, x1, 3.0, 5000, 0.9999, estimator, seed=0)
    assert metrics.homography_corner_error(H_est, H, 640, 480) < 1e-3


def test_the_estimator_is_an_evaluation_setting_recorded_and_changed_by_eval_only(shared_data, tmp_path):
    out = tmp_path / "kitti"
    args = ["megadepth", "--root", shared_data / "megadepth_test_1500", "--scene-info",
            shared_data / "megadepth_test_1500" / "scene_info" / "kitti00_seq.npz", "--matcher", "sift", "--limit", 3,
            "--out", out]
    assert invoke(*args, "--pose-estimator", "poselib").exit_code == 0
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["evaluation"]["estimator"] == "poselib"
    poselib_rows = (out / "per_pair.csv").read_text()
    assert invoke(*args, "--eval-only").exit_code == 0  # re-evaluated with the default, OpenCV
    assert yaml.safe_load((out / "config.yaml").read_text())["evaluation"]["estimator"] == "opencv"
    assert (out / "per_pair.csv").read_text() != poselib_rows  # other estimates, same matches
    line = one_line_error(invoke(*args, "--eval-only", "--pose-estimator", "magic"))
    assert "unknown estimator 'magic'; choose one of opencv, poselib, pycolmap" in line


def test_the_gluefactory_protocol_sets_poselib_at_its_threshold():
    from e3cm_bench.method.protocols import get_protocol

    protocol = get_protocol("gluefactory", "megadepth")
    ev = EvalSettings(**protocol.eval_fields("megadepth"))
    assert ev.estimator == "poselib" and ev.pose_ransac_px == 2.0 and ev.pose_ransac_frame == "matched"
    assert protocol.max_side == {"megadepth": 1600} and protocol.resize_mode("megadepth") == "exact"
