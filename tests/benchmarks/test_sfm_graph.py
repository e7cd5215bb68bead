"""The sfm set checked before any matching, at the command: its pair graph's connected components
(refused when several, each its own bag with --allow-disconnected), and what used to stop the
reconstruction only after every pair was matched (no pycolmap, an image listed twice, a pair
listed both ways, --repeats), images outside the root, a stereo layout's repeated file stems,
a repeated --graph; and `check` of an sfm run against its own baseline.

"Before matching" is asserted as: the run folder holds no matches.h5 (the refusals come while
the set loads, before the folder is even opened).
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from e3cm_bench.benchmarks import get_benchmark
from e3cm_bench.datasets.megadepth import load_scene_info
from helpers import flat, invoke, one_line_error

pytest.importorskip("pycolmap", reason="the sfm benchmark needs pycolmap (the colmap extra)")

KITTI = "megadepth_test_1500"
SCENE_INFO = "megadepth_test_1500/scene_info/kitti00_seq.npz"


@pytest.fixture(scope="module")
def scene(shared_data) -> dict:
    return load_scene_info(shared_data / SCENE_INFO)


@pytest.fixture(scope="module")
def pose_list_graph(shared_data, scene, tmp_path_factory) -> Path:
    """The pose benchmark's own 31 KITTI pairs (the scene_info's pair_infos: frames 3 and 6
    apart) as a --graph file: three chains, frames equal mod 3, that share no image."""
    names = [str(p) for p in scene["image_paths"]]
    path = tmp_path_factory.mktemp("graph") / "kitti_pose_pairs.txt"
    path.write_text("".join(f"{names[i]} {names[j]}\n" for (i, j), *_ in scene["pair_infos"]))
    assert len(path.read_text().splitlines()) == 31
    return path


def scene_paths(shared_data) -> list:
    return list(load_scene_info(shared_data / SCENE_INFO)["image_paths"])


def _sfm(shared_data, out, *args):
    return invoke("sfm", "--root", shared_data / KITTI, "--matcher", "sift", "--out", out, *args)


def _not_matched(out: Path) -> None:
    assert not (out / "matches.h5").exists()


def _numbers(*arrays) -> list[str]:
    return [str(v) for a in arrays for v in np.ravel(a).tolist()]


def _pair_list(path: Path, scene: dict, lines: list[tuple[int, int, str, str]]) -> Path:
    """A SuperGlue-format list: (i, j, name0, name1) with frame i's and j's K and relative pose."""
    K, poses = scene["intrinsics"], scene["poses"]
    path.write_text("".join(" ".join([a, b, "0", "0", *_numbers(K[i], K[j], poses[j] @ np.linalg.inv(poses[i]))])
                            + "\n" for i, j, a, b in lines))
    return path


# ----------------------------------------------------------------------------- the pair graph


def test_a_disconnected_graph_is_refused_in_one_line_before_matching(shared_data, pose_list_graph, tmp_path):
    out = tmp_path / "out"
    line = one_line_error(_sfm(shared_data, out, "--scene-info", shared_data / SCENE_INFO, "--graph", pose_list_graph))
    assert str(pose_list_graph) in line and "3 components that share no image" in line
    assert "{000100, 000103, 000106, ... 7 images}" in line and "{000102, 000105, 000108, ... 6 images}" in line
    assert "--allow-disconnected" in line
    _not_matched(out)


def test_allow_disconnected_makes_each_component_a_bag(shared_data, pose_list_graph, tmp_path):
    # one pair of each chain at the command (3 pairs to match); the whole list's bags below
    names = [str(p) for p in scene_paths(shared_data)]
    graph = tmp_path / "three_chains.txt"
    graph.write_text("".join(f"{names[i]} {names[i + 3]}\n" for i in range(3)))
    out = tmp_path / "out"
    result = _sfm(shared_data, out, "--scene-info", shared_data / SCENE_INFO, "--graph", graph, "--allow-disconnected")
    assert result.exit_code == 0, result.output
    assert "pair graph: 3 components (bags) of 2, 2, 2 images" in flat(result.output)
    dataset = yaml.safe_load((out / "config.yaml").read_text())["dataset"]
    assert dataset["components"] == {"count": 3, "sizes": [2, 2, 2]} and dataset["allow_disconnected"] is True
    pairs = get_benchmark("sfm").load_dataset(shared_data / KITTI, scene_info=shared_data / SCENE_INFO,
                                              graph=pose_list_graph, allow_disconnected=True)
    index = {str(p): i for i, p in enumerate(load_scene_info(shared_data / SCENE_INFO)["image_paths"])}
    for pair in pairs:  # largest first; the two of 7 in the order first met: frames 0 mod 3, then 1 mod 3
        i, j = index[pair.view0], index[pair.view1]
        assert pair.bag == i % 3 == j % 3


def test_a_connected_graph_is_one_bag(shared_data, tmp_path):
    out = tmp_path / "out"
    # --limit applies before the graph is built: the components are those of the pairs run
    result = _sfm(shared_data, out, "--scene-info", shared_data / SCENE_INFO, "--window", "2", "--limit", "3")
    assert result.exit_code == 0, result.output
    assert "pair graph: one component of 3 images" in flat(result.output)
    assert yaml.safe_load((out / "config.yaml").read_text())["dataset"]["components"] == {"count": 1, "sizes": [3]}


def test_a_repeated_graph_option_is_refused(shared_data, pose_list_graph, tmp_path):
    """Before, the last --graph silently won."""
    out = tmp_path / "out"
    line = one_line_error(_sfm(shared_data, out, "--scene-info", shared_data / SCENE_INFO, "--graph", pose_list_graph,
                               "--graph", pose_list_graph))
    assert "--graph is given 2 times" in line
    _not_matched(out)


# ----------------------------------------------------------------------------- refused before matching


def test_missing_pycolmap_is_refused_before_matching(shared_data, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "pycolmap", None)  # `import pycolmap` raises ImportError
    out = tmp_path / "out"
    line = one_line_error(_sfm(shared_data, out, "--scene-info", shared_data / SCENE_INFO, "--window", "1"))
    assert "pycolmap" in line
    _not_matched(out)


def test_an_image_listed_twice_is_refused_before_matching(shared_data, scene, tmp_path):
    paths = np.array(scene["image_paths"], dtype=object)
    paths[4:] = None
    paths[2] = paths[0]
    twice = tmp_path / "twice.npz"
    np.savez(twice, image_paths=paths, intrinsics=scene["intrinsics"], poses=scene["poses"],
             pair_infos=scene["pair_infos"])
    out = tmp_path / "out"
    line = one_line_error(_sfm(shared_data, out, "--scene-info", twice, "--window", "1"))
    assert str(twice) in line and "listed twice (image_paths[0] and image_paths[2])" in line
    _not_matched(out)


def test_a_pair_listed_both_ways_is_refused_before_matching(shared_data, scene, tmp_path):
    names = [str(p) for p in scene["image_paths"][:3]]
    pairs = _pair_list(tmp_path / "pairs.txt", scene, [(0, 1, names[0], names[1]), (1, 2, names[1], names[2]),
                                                       (1, 0, names[1], names[0])])
    out = tmp_path / "out"
    line = one_line_error(_sfm(shared_data, out, "--pairs", pairs))
    assert str(pairs) in line and "join the same two images" in line
    _not_matched(out)


def test_repeats_are_refused_before_matching(shared_data, tmp_path):
    out = tmp_path / "out"
    line = one_line_error(_sfm(shared_data, out, "--scene-info", shared_data / SCENE_INFO, "--window", "1",
                               "--repeats", "2"))
    assert "--repeats does not apply to sfm" in line
    _not_matched(out)


# ----------------------------------------------------------------------------- where images may be


def test_images_outside_the_root_need_absolute_paths(shared_data, scene, tmp_path):
    names = [str(p) for p in scene["image_paths"][:3]]
    inside = shared_data / KITTI
    # '..' out of the root given (scene_info/), and absolute paths into another folder
    for root, (a, b, c) in ((inside / "scene_info", [f"../{n}" for n in names]),
                            (tmp_path, [str(inside / n) for n in names])):
        pairs = _pair_list(tmp_path / "pairs.txt", scene, [(0, 1, a, b), (1, 2, b, c)])
        out = tmp_path / "out"
        line = one_line_error(invoke("sfm", "--root", root, "--pairs", pairs, "--matcher", "sift", "--out", out))
        assert str(pairs) in line and "lies outside the image root" in line and "--absolute-paths" in line
        _not_matched(out)
    result = invoke("sfm", "--root", tmp_path, "--pairs", pairs, "--matcher", "sift", "--out", tmp_path / "anywhere",
                    "--absolute-paths", "--limit", "1")
    assert result.exit_code == 0, result.output
    assert yaml.safe_load((tmp_path / "anywhere" / "config.yaml").read_text())["dataset"]["absolute_paths"] is True
    dataset = get_benchmark("sfm").load_dataset(tmp_path, pairs=pairs, absolute_paths=True)
    assert [v.name for v in dataset.views] == [(inside / n).as_posix() for n in names]


def test_a_stereo_layout_with_equal_file_stems_is_usable(shared_data, scene, tmp_path):
    """image_0/N.png and image_1/N.png: the pairs are named by the images' paths where file
    stems repeat (before, two pairs got one name and the set was refused)."""
    root = tmp_path / "stereo"
    files = [Path(str(p)).name for p in scene["image_paths"][:3]]
    for camera in ("image_0", "image_1"):
        (root / camera).mkdir(parents=True)
        for name in files:
            shutil.copy(shared_data / KITTI / "Undistorted_SfM" / "kitti00" / "images" / name, root / camera / name)
    n = [f"image_{c}/{f}" for c in (0, 1) for f in files]
    pairs = _pair_list(tmp_path / "stereo.txt", scene, [(0, 1, n[0], n[1]), (1, 2, n[1], n[2]), (0, 1, n[3], n[4]),
                                                        (1, 2, n[4], n[5]), (0, 1, n[0], n[4])])
    out = tmp_path / "out"
    result = invoke("sfm", "--root", root, "--pairs", pairs, "--matcher", "sift", "--out", out, "--limit", "1")
    assert result.exit_code == 0, result.output
    dataset = get_benchmark("sfm").load_dataset(root, pairs=pairs)
    assert [p.name for p in dataset] == ["stereo.txt/image_0/000100--image_0/000101",
                                         "stereo.txt/image_0/000101--image_0/000102",
                                         "stereo.txt/image_1/000100--image_1/000101",
                                         "stereo.txt/image_1/000101--image_1/000102",
                                         "stereo.txt/image_0/000100--image_1/000101"]
    assert len(dataset.views) == 6


# ----------------------------------------------------------------------------- check


def test_check_passes_an_sfm_run_against_its_own_baseline(shared_data, tmp_path):
    """Before, `check` stopped: no tolerance for sfm's mAA."""
    run = tmp_path / "run"
    result = _sfm(shared_data, run, "--scene-info", shared_data / SCENE_INFO, "--window", "2", "--limit", "3")
    assert result.exit_code == 0, result.output
    baseline = tmp_path / "baseline.csv"
    assert invoke("check", run, "--baseline", baseline, "--update").exit_code == 0
    result = invoke("check", run, "--baseline", baseline)
    assert result.exit_code == 0, result.output
    assert "no regression: 4 metrics of 1 runs" in flat(result.output)
