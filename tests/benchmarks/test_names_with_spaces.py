"""Names with spaces (issue 70, item 1): COLMAP's pair list is split at spaces, so images named
'a b.png' verified with 0 matches and `reconstruct` registered none, exit 0. The verification now
goes through pycolmap's API (interchange/colmap.py verify_pairs), for `reconstruct` and for
`sfm --verification colmap` alike, and the pair list the toolkit writes quotes such names."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from helpers import invoke

pytest.importorskip("pycolmap")

FRAMES = ("000100", "000101", "000102", "000103")


@pytest.fixture
def spaced(shared_data: Path, tmp_path: Path) -> Path:
    images = shared_data / "megadepth_test_1500" / "Undistorted_SfM" / "kitti00" / "images"
    folder = tmp_path / "my photos"
    folder.mkdir()
    for frame in FRAMES:
        shutil.copy(images / f"{frame}.png", folder / f"frame {frame} (copy).png")
    return folder


def test_names_with_spaces_reconstruct_and_their_pair_list_reads_back(spaced, tmp_path):
    out = tmp_path / "out"
    result = invoke("reconstruct", spaced, "--out", out, "--matcher", "sift", "--window", 2)
    assert result.exit_code == 0, result.output
    assert f"{len(FRAMES)} of {len(FRAMES)} images registered" in " ".join(result.output.split())
    lines = (out / "pairs.txt").read_text().splitlines()
    assert lines[0] == "'frame 000100 (copy).png' 'frame 000101 (copy).png'"
    again = invoke("reconstruct", spaced, "--out", tmp_path / "again", "--matcher", "sift", "--pairs", out / "pairs.txt")
    assert again.exit_code == 0, again.output
    assert f"{len(FRAMES)} of {len(FRAMES)} images registered" in " ".join(again.output.split())


def test_verify_pairs_gives_verify_matches_geometries(tmp_path, spaced):
    """On names without spaces the per-pair API and COLMAP's own verify_matches agree pair for pair."""
    import numpy as np
    import pycolmap

    from e3cm_bench.interchange.colmap import verify_pairs

    plain = tmp_path / "plain"
    plain.mkdir()
    for k, image in enumerate(sorted(spaced.iterdir())):
        shutil.copy(image, plain / f"{k}.png")
    out = tmp_path / "run"
    assert invoke("reconstruct", plain, "--out", out, "--matcher", "sift", "--window", 2).exit_code == 0
    pairs = [tuple(line.split()) for line in (out / "pairs.txt").read_text().splitlines()]
    copies = [tmp_path / "a.db", tmp_path / "b.db"]
    for copy in copies:
        shutil.copy(out / "database.db", copy)
        with pycolmap.Database.open(str(copy)) as db:
            db.clear_two_view_geometries()
    options = pycolmap.TwoViewGeometryOptions()
    options.ransac.random_seed = 0
    pycolmap.verify_matches(str(copies[0]), str(out / "pairs.txt"), options)
    verify_pairs(pycolmap, copies[1], pairs, options)
    with pycolmap.Database.open(str(copies[0])) as a, pycolmap.Database.open(str(copies[1])) as b:
        ids = {image.name: image.image_id for image in a.read_all_images()}
        for name0, name1 in pairs:
            ga, gb = (db.read_two_view_geometry(ids[name0], ids[name1]) for db in (a, b))
            assert ga.config == gb.config and np.array_equal(ga.inlier_matches, gb.inlier_matches), (name0, name1)
