"""--protocol gluefactory on HPatches: the ground-truth H applied to corner-convention
coordinates and glue-factory's match precision (gluefactory/eval/utils.py
eval_matches_homography, geometry/homography.py sym_homography_error), where half a pixel
decides whether a match counts."""

from __future__ import annotations

import shutil

import numpy as np
import pandas as pd
import pytest
import yaml

from e3cm_bench.geometry import metrics
from e3cm_bench.benchmarks import EvalSettings, get_benchmark
from e3cm_bench.method.protocols import get_protocol
from e3cm_bench.datasets.base import Pair
from e3cm_bench.ground.matches import Matches
from helpers import invoke

# image 0 -> image 1: four times larger, shifted; the true matches below are exact in the
# centre convention (ours), and 1.5 px off per axis in glue-factory's
H = np.array([[4.0, 0.0, 3.0], [0.0, 4.0, -2.0], [0.0, 0.0, 1.0]])


def gluefactory_precision(k0: np.ndarray, k1: np.ndarray, H: np.ndarray, t: float) -> float:
    """glue-factory's prec@t: keypoints in its corner convention (ours + 0.5), the mean of the
    forward and backward transfer distances, strictly below t; written here from its formula."""
    c0, c1 = k0 + 0.5, k1 + 0.5
    forward = c0 @ H[:2, :2].T + H[:2, 2]
    backward_h = np.c_[c1, np.ones(len(c1))] @ np.linalg.pinv(H.T)
    backward = backward_h[:, :2] / backward_h[:, 2:]
    error = (np.linalg.norm(forward - c1, axis=1) + np.linalg.norm(backward - c0, axis=1)) / 2
    return float(np.mean(error < t))


def synthetic_pair() -> tuple[Pair, Matches]:
    grid = np.stack(np.meshgrid(np.arange(10, 90, 8.0), np.arange(10, 60, 10.0)), -1).reshape(-1, 2)
    k0 = grid
    k1 = k0 * 4 + np.array([3.0, -2.0])
    wrong = np.array([[20.0, 20.0], [50.0, 30.0]])
    k0 = np.r_[k0, wrong]
    k1 = np.r_[k1, wrong * 4 + 50]  # far off
    pair = Pair(name="v_synthetic/1-2", image0=None, image1=None, H=H, meta={"sequence": "v_synthetic"})
    matches = Matches(k0.astype(np.float32), k1.astype(np.float32), np.ones(len(k0), np.float32))
    matches.info["size0"] = (100, 70)
    return pair, matches


def test_the_preset_scores_matches_as_gluefactory_does_where_the_half_pixel_decides():
    hpatches = get_benchmark("hpatches")
    pair, matches = synthetic_pair()
    k0, k1 = matches.keypoints0.astype(np.float64), matches.keypoints1.astype(np.float64)
    ev = EvalSettings(**get_protocol("gluefactory", "hpatches").eval_fields("hpatches"))
    assert ev.homography_pixel_origin == "corner" and ev.match_precision_px == (1.0, 3.0)
    row = hpatches.evaluate_pair(pair, matches, ev)
    expected = {t: gluefactory_precision(k0, k1, H, t) for t in (1.0, 3.0)}
    assert row["prec@1px"] == expected[1.0] == 0.0  # 1.33 px in glue-factory's convention
    assert row["prec@3px"] == expected[3.0] == 50 / 52
    ours = hpatches.evaluate_pair(pair, matches, EvalSettings())
    assert ours["mma@1"] == 50 / 52 and "prec@1px" not in ours  # the default protocol: exact, no new columns
    assert row["mma@1"] == 0.0  # the preset's MMA applies H in the corner convention too
    summary = hpatches.summarize([row, {**row, "prec@1px": 0.5}], ev)
    assert summary["prec@1px"] == 0.25 and summary["mprec@1px"] == 0.25  # glue-factory reports the median
    assert hpatches.pair_columns(ev)[-2:] == ["prec@1px", "prec@3px"]


def test_the_corner_error_takes_the_corners_of_the_corner_convention():
    """glue-factory's homography_corner_error: corners (0, 0), (w, 0), (w, h), (0, h)."""
    w, h = 100, 70
    other = H @ np.array([[1.0, 0.01, 0.5], [0.0, 1.0, -0.3], [1e-4, 0.0, 1.0]])
    corners = np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float64)

    def warp(M, p):
        q = np.c_[p, np.ones(len(p))] @ M.T
        return q[:, :2] / q[:, 2:]

    expected = np.mean(np.linalg.norm(warp(other, corners) - warp(H, corners), axis=1))
    assert metrics.homography_corner_error(other, H, w + 1, h + 1) == pytest.approx(expected, rel=1e-12)


def test_protocol_gluefactory_runs_on_hpatches_and_is_recorded(shared_data, tmp_path):
    root = shared_data / "hpatches-sequences-release"
    select = ["--root", root, "--sequences", "v_boat", "--limit", "2"]
    out = tmp_path / "sift"
    assert invoke("hpatches", *select, "--out", out, "--matcher", "sift").exit_code == 0
    ours = pd.read_csv(out / "per_pair.csv")
    gf = tmp_path / "gf"
    shutil.copytree(out, gf)
    result = invoke("hpatches", *select, "--out", gf, "--matcher", "sift", "--eval-only", "--protocol", "gluefactory")
    assert result.exit_code == 0 and "protocol gluefactory" in result.output
    evaluation = yaml.safe_load((gf / "config.yaml").read_text())["evaluation"]
    assert evaluation["protocol"] == "gluefactory" and evaluation["homography_pixel_origin"] == "corner"
    rows = pd.read_csv(gf / "per_pair.csv")
    summary = pd.read_csv(gf / "summary.csv").iloc[0]
    assert summary["mprec@1px"] == pytest.approx(float(np.median(rows["prec@1px"])))
    assert (rows["prec@1px"] < ours["mma@1"]).all()  # v_boat zooms: glue-factory's half pixel costs matches
