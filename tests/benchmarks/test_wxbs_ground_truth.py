"""WxBS ground truth is checked against its images: a correspondence far outside an image (a
typo, or a file meant for another pair) is one line naming corrs.txt, where it used to score
the pair mAA 0 without a word; --skip-bad lists the pair and scores the others."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from PIL import Image

from e3cm_bench.benchmarks.wxbs import EDGE_TOLERANCE_PX, WxBS
from e3cm_bench.datasets.base import DatasetError
from helpers import invoke, one_line_error

PAIRS = ("WGABS/kremlin", "WGABS/kyiv")


def copy_pairs(wxbs_root: Path, folder: Path) -> Path:
    for pair in PAIRS:
        shutil.copytree(wxbs_root / "v1.1" / pair, folder / "v1.1" / pair)
    return folder


def move_one_point(corrs_file: Path, side: int, by: float) -> None:
    """The third correspondence's point on image `side` (0 or 1) moved by `by` px in x."""
    corrs = np.loadtxt(corrs_file, ndmin=2)
    corrs[2, 2 * side] += by
    np.savetxt(corrs_file, corrs)


def test_a_correspondence_a_million_pixels_off_the_image_is_one_line(wxbs_root, tmp_path):
    root = copy_pairs(wxbs_root, tmp_path / "wxbs")
    corrs = root / "v1.1" / "WGABS" / "kyiv" / "corrs.txt"
    move_one_point(corrs, 1, 1e6)
    line = one_line_error(invoke("wxbs", "--root", root, "--out", tmp_path / "run", "--matcher", "sift"))
    assert f"{corrs}: 1 of " in line and "correspondences lie outside image 02" in line and "first on row 3" in line
    assert "(1 of 2 pairs have bad input); pass --skip-bad" in line
    assert not (tmp_path / "run" / "per_pair.csv").exists()

    result = invoke("wxbs", "--root", root, "--out", tmp_path / "skip", "--matcher", "sift", "--skip-bad")
    assert result.exit_code == 0, result.output
    assert list(pd.read_csv(tmp_path / "skip" / "per_pair.csv")["pair"]) == ["WGABS/kremlin"]
    skipped = pd.read_csv(tmp_path / "skip" / "skipped.csv")
    assert list(skipped["pair"]) == ["WGABS/kyiv"] and "outside image 02" in skipped.iloc[0, 1]


def test_the_release_lies_within_its_images_and_a_slip_past_the_border_is_kept(wxbs_root, tmp_path):
    assert len(WxBS(wxbs_root, split="all")) == 33  # every pair of the release passes the check
    root = copy_pairs(wxbs_root, tmp_path / "wxbs")
    corrs = root / "v1.1" / "WGABS" / "kremlin" / "corrs.txt"
    original = corrs.read_text()
    x = np.loadtxt(corrs, ndmin=2)[2, 0]
    with Image.open(next(corrs.parent.glob("01.*"))) as image:
        width = image.size[0]
    move_one_point(corrs, 0, width + EDGE_TOLERANCE_PX - x)  # on the tolerance's edge: kept
    assert len(WxBS(root, split="all")) == 2
    corrs.write_text(original)
    move_one_point(corrs, 0, width + EDGE_TOLERANCE_PX + 1 - x)  # a pixel further: refused
    with pytest.raises(DatasetError, match="outside image 01"):
        WxBS(root, split="all")
