"""Exports that the consumer can build on: COLMAP's incremental mapper reconstructs the KITTI
frames from the COLMAP export of a SIFT run; hloc's one-match-per-keypoint layout keeps a pair
that matched one keypoint twice, and import gets the run's order back (or refuses a damaged one)."""

from __future__ import annotations

from itertools import combinations
from types import SimpleNamespace

import h5py
import numpy as np
import pytest

from e3cm_bench.geometry.two_view import rotation_angle_deg
from e3cm_bench.interchange import HlocSource
from e3cm_bench.interchange.base import ExportItem
from e3cm_bench.interchange.hloc import ORDER_KEY, write_hloc
from e3cm_bench.ground.matches import Matches, MatchesError
from helpers import invoke


@pytest.fixture(scope="module")
def kitti_window(shared_data, tmp_path_factory):
    """A SIFT run over the 20 shared KITTI 00 frames, each matched to the next two: the shared
    pair list joins frames 3 and 6 apart only, three chains (frames equal mod 3) that no mapper
    can put in one model, so the pairs are made here from the same scene_info."""
    root = shared_data / "megadepth_test_1500"
    info = dict(np.load(root / "scene_info" / "kitti00_seq.npz", allow_pickle=True))
    n = len(info["image_paths"])
    pairs = [((i, i + step), 0.5, np.zeros(1)) for step in (1, 2) for i in range(n - step)]
    info["pair_infos"] = np.empty(len(pairs), dtype=object)
    info["pair_infos"][:] = pairs
    folder = tmp_path_factory.mktemp("kitti-window")
    np.savez(folder / "kitti00_window.npz", **info)
    out = folder / "sift"
    assert invoke("megadepth", "--root", root, "--scene-info", folder / "kitti00_window.npz", "--out", out,
                  "--matcher", "sift").exit_code == 0
    return out, root, info


@pytest.mark.slow  # 19 s with its KITTI window in the fast set under a load of about 7 on the shared 2-core machine (docs/development.md, Testing)
def test_colmaps_mapper_registers_the_kitti_frames_in_one_model(kitti_window, tmp_path):
    """Before one keypoint list per image the mapper made no model of this export (0 of 20:
    docs/interchange.md); now one model holds most frames, with relative rotations close to
    the ground truth."""
    pycolmap = pytest.importorskip("pycolmap", reason="the colmap extra (pycolmap) is not installed")
    from e3cm_bench.interchange.colmap import mapper_options

    run, root, info = kitti_window
    result = invoke("export", run, tmp_path / "colmap", "--to", "colmap")
    assert result.exit_code == 0 and "one keypoint list per image" in result.output
    models = pycolmap.incremental_mapping(str(tmp_path / "colmap" / "database.db"), str(root), str(tmp_path / "sparse"),
                                          options=mapper_options(pycolmap))
    assert models, "the mapper made no model"
    model = max(models.values(), key=lambda m: m.num_reg_images())
    n = len(info["image_paths"])
    assert model.num_reg_images() >= 0.9 * n  # measured: 20 of 20
    truth = {str(p): np.asarray(T, np.float64)[:3, :3] for p, T in zip(info["image_paths"], info["poses"])}
    rotations = {image.name: image.cam_from_world().rotation.matrix() for image in model.images.values() if image.has_pose}
    errors = [rotation_angle_deg(rotations[b] @ rotations[a].T, truth[b] @ truth[a].T)
              for a, b in combinations(sorted(rotations), 2)]
    assert np.median(errors) < 1.5  # degrees; measured 0.47
    assert np.mean([p.track.length() for p in model.points3D.values()]) > 3  # tracks longer than one pair


def synthetic_items(tmp_path):
    """Two pairs of image a: the first matches a's point (10, 10) twice (to two points of b),
    and the second shares it; every score distinct, so that order shows."""
    root = tmp_path / "data"
    a, b, c = (np.array(p, np.float32) for p in ([[10, 10], [10, 10], [20, 5]], [[1, 1], [2, 2], [3, 3]],
                                                  [[10, 10], [7, 7]]))
    items, pairs = [], []
    for name, k0, k1, scores, other in (("a-b", a, b, [0.9, 0.8, 0.7], "b.png"),
                                        ("a-c", a[[2, 0]], c, [0.6, 0.5], "c.png")):
        pair = SimpleNamespace(name=name, image0=root / "a.png", image1=root / other)
        items.append(ExportItem(name, pair, "a.png", other, (40, 30), (40, 30),
                                Matches(k0, k1, np.array(scores, np.float32))))
        pairs.append(pair)
    return root, items, pairs


def test_a_keypoint_matched_twice_in_a_pair_gets_its_own_entry_and_the_order_comes_back(tmp_path):
    root, items, pairs = synthetic_items(tmp_path)
    out = tmp_path / "hloc"
    out.mkdir()
    write_hloc(out, items)
    with h5py.File(out / "features.h5", "r") as f:
        # a: (10, 10), (20, 5), then the second match of (10, 10) in pair a-b, appended
        assert f["a.png"]["keypoints"][()].tolist() == [[10, 10], [20, 5], [10, 10]]
    with h5py.File(out / "matches.h5", "r") as f:
        assert f["a.png/b.png"]["matches0"][()].tolist() == [0, 2, 1]  # every match, one per keypoint
        assert f["a.png/c.png"]["matches0"][()].tolist() == [1, 0, -1]
        assert f["a.png/c.png"][ORDER_KEY][()].tolist() == [1, 0]  # the run's order: (20, 5) first
    source = HlocSource(out / "features.h5", out / "matches.h5")
    for item, pair in zip(items, pairs):
        back = source.read(pair, root)
        np.testing.assert_array_equal(back.keypoints0, item.matches.keypoints0)
        np.testing.assert_array_equal(back.keypoints1, item.matches.keypoints1)
        np.testing.assert_array_equal(back.scores, item.matches.scores)
    with h5py.File(out / "matches.h5", "r+") as f:
        del f["a.png/c.png"][ORDER_KEY]
        f["a.png/c.png"].create_dataset(ORDER_KEY, data=np.array([0, 0]))
    with pytest.raises(MatchesError, match=f"{ORDER_KEY}: not the 2 matched keypoints of matches0, each once"):
        source.read(pairs[1], root)
    with h5py.File(out / "matches.h5", "r+") as f:
        del f["a.png/c.png"][ORDER_KEY]  # a file without it (hloc's own): keypoint order
    back = source.read(pairs[1], root)
    assert back.keypoints0.tolist() == [[10, 10], [20, 5]]
