"""Bounds before work (issue 70, item 2): a count or radius past its bound is one line before
anything loads (the ranges of their evaluation options: benchmarks/eval_options.py RECONSTRUCTION_BOUNDS)."""

from __future__ import annotations

import time

import pytest

from helpers import invoke, one_line_error


@pytest.mark.parametrize("option, value, words", [
    ("--mapper-seeds", "1000000000", "--mapper-seeds must be a whole number, from 1 to 100, got 1000000000"),
    ("--merge-px", "1e9", "--merge-px must be a finite number, from 0 to 50, got 1000000000.0"),
])
def test_sfm_refuses_an_unbounded_value_before_matching(shared_data, tmp_path, option, value, words):
    root = shared_data / "megadepth_test_1500"
    extra = ["--merge", "radius"] if option == "--merge-px" else []
    started = time.perf_counter()
    line = one_line_error(invoke("sfm", "--root", root, "--scene-info", root / "scene_info" / "kitti00_seq.npz",
                                 "--window", 2, "--matcher", "sift", "--out", tmp_path / "run", *extra, option, value))
    assert words in line
    assert not (tmp_path / "run" / "matches.h5").exists() and time.perf_counter() - started < 60


def test_reconstruct_refuses_a_merge_radius_past_the_bound(tmp_path):
    import numpy as np
    from PIL import Image

    for k in range(3):
        Image.fromarray(np.random.default_rng(k).integers(0, 255, (64, 64, 3), dtype=np.uint8)).save(tmp_path / f"{k}.png")
    line = one_line_error(invoke("reconstruct", tmp_path, "--out", tmp_path / "out", "--matcher", "sift",
                                 "--merge-px", "1e9"))
    assert "--merge-px must be a finite number, from 0 to 50" in line and not (tmp_path / "out" / "matches.h5").exists()
