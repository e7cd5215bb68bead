"""Stereo rig self-calibration: the estimator, the readers, and `calibrate` end to end."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import yaml

from e3cm_bench.apps.calibration import estimate_extrinsics, extrinsic_errors, vertical_disparity
from e3cm_bench.datasets.base import DatasetError
from e3cm_bench.datasets.stereo import load_stereo_sequence
from e3cm_bench.apps.synth.stereo import rig_extrinsics
from helpers import invoke, one_line_error

K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])


def rig_matches(R, t, n=2000, noise_px=0.5, outliers=0.0, seed=0):
    """Matches of random points 3..20 m in front of the left camera, with pixel noise and a
    share of outliers (right points moved 20..80 px in a random direction)."""
    rng = np.random.default_rng(seed)
    X = np.stack([rng.uniform(-8, 8, n), rng.uniform(-3, 3, n), rng.uniform(3, 20, n)], 1)
    x0 = X @ K.T
    x0 = x0[:, :2] / x0[:, 2:]
    Xr = X @ R.T + t
    x1 = Xr @ K.T
    x1 = x1[:, :2] / x1[:, 2:]
    x0 += rng.normal(0, noise_px, x0.shape)
    x1 += rng.normal(0, noise_px, x1.shape)
    bad = rng.random(n) < outliers
    angle = rng.uniform(0, 2 * np.pi, bad.sum())
    x1[bad] += rng.uniform(20, 80, bad.sum())[:, None] * np.stack([np.cos(angle), np.sin(angle)], 1)
    return x0, x1


def worst(errors: dict) -> tuple[float, float]:
    return max(abs(errors[k]) for k in ("yaw", "pitch", "roll")), max(abs(errors[k]) for k in ("tx", "ty", "tz"))


def test_exact_geometry_recovers_the_drifted_rig():
    R, t = rig_extrinsics(np.random.default_rng(3))
    angles = np.degrees(cv2.Rodrigues(R)[0].ravel())
    assert np.all((np.abs(angles) > 0.6) & (np.abs(angles) < 1.4))  # about 1 degree in each angle
    x0, x1 = rig_matches(R, t)
    cv2.setRNGSeed(0)
    estimate = estimate_extrinsics(x0, x1, K, K)
    rotation, translation = worst(extrinsic_errors(estimate["R"], estimate["t"], R, t))
    print(f"0.5 px noise: rotation {rotation:.4f} deg, translation {translation:.5f}")
    # Measured: 0.012 deg and 0.0007 with 2000 matches at 0.5 px noise.
    assert rotation < 0.03 and translation < 0.002
    before, after = vertical_disparity(x0, x1, K, K, estimate["R"], estimate["t"], (640, 480))
    # The drift shows before; after, what is left is the noise: the median |difference| of two
    # 0.5 px noises is 0.48 px (measured 0.51).
    assert before > 3 and after < 0.6


def test_outliers_hurt_and_the_robust_steps_limit_the_damage():
    R, t = rig_extrinsics(np.random.default_rng(5))
    x0, x1 = rig_matches(R, t, outliers=0.3, seed=1)
    cv2.setRNGSeed(0)
    robust = worst(extrinsic_errors(*_Rt(estimate_extrinsics(x0, x1, K, K)), R, t))
    plain = worst(extrinsic_errors(*_Rt(estimate_extrinsics(x0, x1, K, K, robust=False)), R, t))
    clean = worst(extrinsic_errors(*_Rt(estimate_extrinsics(*rig_matches(R, t, seed=1), K, K)), R, t))
    print(f"30% outliers: robust {robust}, plain least squares {plain}; clean {clean}")
    # Measured: robust 0.004 deg (clean data: 0.010); 8-point + plain least squares 0.15 deg, 35x worse.
    assert plain[0] > 10 * robust[0] and plain[0] > 0.1
    assert robust[0] < clean[0] + 0.02 and robust[1] < 0.005


def _Rt(estimate):
    return estimate["R"], estimate["t"]


# --------------------------------------------------------------------------- readers


def write_images(folder: Path, names) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        cv2.imwrite(str(folder / name), np.full((48, 64, 3), 128, np.uint8))


def test_kitti_odometry_layout(tmp_path):
    root = tmp_path / "dataset" / "sequences" / "00"
    write_images(root / "image_0", ["000000.png", "000001.png"])
    write_images(root / "image_1", ["000000.png", "000001.png"])
    # KITTI's rectified rig: P1 = K [I | (-b, 0, 0)], so P1[0, 3] = -fx b (b = 0.54 m).
    P0 = np.hstack([K, np.zeros((3, 1))])
    P1 = P0.copy()
    P1[0, 3] = -500.0 * 0.54
    lines = [f"P{i}: " + " ".join(f"{v:.12e}" for v in P.ravel()) for i, P in enumerate((P0, P1, P0, P1))]
    (root / "calib.txt").write_text("\n".join(lines + ["Tr: " + " ".join(["0"] * 12)]) + "\n")
    sequence = load_stereo_sequence(root)
    assert sequence.layout == "kitti-odometry" and len(sequence) == 2
    np.testing.assert_allclose(sequence.K0, K)
    np.testing.assert_allclose(sequence.R, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(sequence.t, [-0.54, 0, 0], atol=1e-9)
    (root / "image_1" / "000001.png").unlink()
    with pytest.raises(DatasetError, match="right image missing"):
        load_stereo_sequence(root)


KITTI_RAW_CALIB = """calib_time: 09-Jan-2012 13:57:47
corner_dist: 9.950000e-02
S_00: 1.392000e+03 5.120000e+02
K_00: 9.842439e+02 0.000000e+00 6.900000e+02 0.000000e+00 9.808141e+02 2.331966e+02 0.000000e+00 0.000000e+00 1.000000e+00
D_00: -3.728755e-01 2.037299e-01 2.219027e-03 1.383707e-03 -7.233722e-02
R_00: 1.000000e+00 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00
T_00: 2.573699e-16 -1.059758e-16 1.614870e-16
K_01: 9.895267e+02 0.000000e+00 7.020000e+02 0.000000e+00 9.878386e+02 2.455590e+02 0.000000e+00 0.000000e+00 1.000000e+00
R_01: 9.993513e-01 1.860866e-02 -3.083487e-02 -1.887662e-02 9.997863e-01 -8.421873e-03 3.067156e-02 8.998467e-03 9.994890e-01
T_01: -5.370000e-01 4.822061e-03 -1.252488e-02
P_rect_00: 7.215377e+02 0.000000e+00 6.095593e+02 0.000000e+00 0.000000e+00 7.215377e+02 1.728540e+02 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00 0.000000e+00
P_rect_01: 7.215377e+02 0.000000e+00 6.095593e+02 -3.875744e+02 0.000000e+00 7.215377e+02 1.728540e+02 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00 0.000000e+00
"""


def test_kitti_raw_layout_rectified_and_not(tmp_path):
    date = tmp_path / "2011_09_26"
    drive = date / "2011_09_26_drive_0001_sync"
    write_images(drive / "image_00" / "data", ["0000000000.png"])
    write_images(drive / "image_01" / "data", ["0000000000.png"])
    (date / "calib_cam_to_cam.txt").write_text(KITTI_RAW_CALIB)  # in the date folder, as KITTI ships it
    rectified = load_stereo_sequence(drive)
    assert rectified.layout == "kitti-raw-rectified"
    np.testing.assert_allclose(rectified.R, np.eye(3), atol=1e-9)
    np.testing.assert_allclose(rectified.t, [-3.875744e+02 / 7.215377e+02, 0, 0], atol=1e-9)
    raw = load_stereo_sequence(drive, unrectified=True)
    assert raw.layout == "kitti-raw"
    assert raw.K1[0, 2] == 7.02e2 and abs(raw.t[0] + 0.537) < 1e-9 and abs(np.linalg.det(raw.R) - 1) < 1e-5


def test_not_a_stereo_sequence(tmp_path):
    with pytest.raises(DatasetError, match="not a stereo sequence"):
        load_stereo_sequence(tmp_path)


# --------------------------------------------------------------------------- end to end


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("stereo") / "seq"
    result = invoke("synth", "stereo", "--out", root, "--frames", 6, "--seed", 2)
    assert result.exit_code == 0
    return root


def test_synthetic_sequence_is_kitti_shaped_and_exact(synthetic):
    sequence = load_stereo_sequence(synthetic)
    assert sequence.layout == "kitti-odometry" and len(sequence) == 6
    assert len((synthetic / "poses.txt").read_text().splitlines()) == 6
    angles = np.degrees(cv2.Rodrigues(sequence.R)[0].ravel())
    assert np.all((np.abs(angles) > 0.6) & (np.abs(angles) < 1.4))  # about 1 degree each
    assert abs(np.linalg.norm(sequence.t) - 0.54) < 0.02


@pytest.mark.slow  # 52 s alone on a loaded 2-core machine (docs/development.md, Testing)
def test_calibrate_end_to_end_with_sift(synthetic, tmp_path):
    out = tmp_path / "cal"
    result = invoke("calibrate", "--root", synthetic, "--out", out, "--matcher", "sift", "--frames", 1, "--frames", 5)
    assert result.exit_code == 0
    windows = pd.read_csv(out / "windows.csv")
    assert list(windows.columns[:9]) == ["frames", "first_frame", "n_matches", "yaw", "pitch", "roll", "tx", "ty", "tz"]
    assert sorted(windows.groupby("frames").size().items()) == [(1, 6), (5, 2)]  # windows slide by one frame
    summary = pd.read_csv(out / "summary.csv").set_index("frames")
    print(summary.to_string())
    # Measured on this sequence (SIFT, 5 frames): rotation 0.027 deg, unit t 0.0068, median vertical
    # disparity 8.9 px -> 0.11 px (0.11 with the true extrinsics).
    assert summary.loc[5, "rotation"] < 0.1 and summary.loc[5, "translation"] < 0.02
    assert summary.loc[5, "vdisp_before"] > 3 and summary.loc[5, "vdisp_after"] < 0.3
    assert summary.loc[5, "rotation"] <= summary.loc[1, "rotation"] + 0.1  # pooling frames does not hurt
    for name in ("calibration_boxplot.png", "calibration_vs_frames.png", "sift/matches.h5", "sift/config.yaml"):
        assert (out / name).is_file(), name
    import platform

    if platform.libc_ver()[0] == "glibc":  # the rig's matching keeps freed memory as a benchmark run does
        assert yaml.safe_load((out / "sift" / "config.yaml").read_text())["environment"]["allocator"].startswith("glibc, freed memory kept")
    again = invoke("calibrate", "--root", synthetic, "--out", out, "--matcher", "sift", "--frames", 1, "--frames", 5)
    assert again.exit_code == 0 and "matching (" not in again.output  # matches are reused
    line = one_line_error(invoke("calibrate", "--root", synthetic, "--out", out, "--matcher", "sift", "--frames", 10))
    assert "6 frames" in line and "10" in line
    # a second run with another matcher joins the folder's set: the top-level tables hold both
    other = invoke("calibrate", "--root", synthetic, "--out", out, "--matcher", "direct", "--backbone", "efficientnet_lite0",
                   "--max-side", 480, "--frames", 1, "--frames", 5)
    assert other.exit_code == 0, other.output
    summary = pd.read_csv(out / "summary.csv")
    assert set(summary["method"]) == {"sift", "direct [efficientnet_lite0]"} and len(summary) == 4
    assert set(pd.read_csv(out / "windows.csv")["method"]) == {"sift", "direct [efficientnet_lite0]"}
    # --set reaches the deep matchers and shows in the label
    refined = invoke("calibrate", "--root", synthetic, "--out", out, "--matcher", "e3cm-ransac",
                     "--backbone", "efficientnet_lite0", "--max-side", 480, "--frames", 1, "--frames", 5, "--set", "refine=ncc")
    assert refined.exit_code == 0, refined.output
    assert "e3cm-ransac refine=ncc [efficientnet_lite0]" in set(pd.read_csv(out / "summary.csv")["method"])
    line = one_line_error(invoke("calibrate", "--root", synthetic, "--out", out, "--matcher", "e3cm-ransac",
                                 "--backbone", "efficientnet_lite0", "--set", "refine=bogus"))
    assert "refine must be one of" in line
    # other settings in the same folder are refused, and nothing there changes
    line = one_line_error(invoke("calibrate", "--root", synthetic, "--out", out, "--matcher", "sift", "--frames", 2))
    assert "calibrate.yaml: this folder holds a calibration of another sequence or with other settings" in line
    assert set(pd.read_csv(out / "summary.csv")["method"]) == {"sift", "direct [efficientnet_lite0]",
                                                               "e3cm-ransac refine=ncc [efficientnet_lite0]"}
