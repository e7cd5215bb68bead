"""One ground-truth rule for every source (datasets/truth.py), checked at the commands.

A COLMAP model's zero quaternion was read as the identity (the run scored, exit 0), and its
focal length of 0 or -718 was accepted (every pair failed without a word) where a scene_info
with the same K was refused. Each source now refuses the same values with the same words,
in one line naming the file and the entry, before any matching."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from e3cm_bench.datasets.base import DatasetError
from e3cm_bench.datasets.megadepth import load_scene_info
from e3cm_bench.datasets.truth import check_intrinsics, check_pose, check_quaternion, check_rotation
from helpers import invoke, one_line_error

KITTI = "megadepth_test_1500"
SCENE_INFO = "megadepth_test_1500/scene_info/kitti00_seq.npz"


def _kitti(shared_data, n: int = 3):
    scene = load_scene_info(shared_data / SCENE_INFO)
    return scene, [(str(scene["image_paths"][i]), scene["intrinsics"][i], scene["poses"][i]) for i in range(n)]


def _colmap_model(folder: Path, views) -> Path:
    """A text model of one PINHOLE camera per image, written by pycolmap from (name, K, pose)."""
    pycolmap = pytest.importorskip("pycolmap", reason="reading a COLMAP model needs pycolmap")
    model = pycolmap.Reconstruction()
    for index, (name, K, pose) in enumerate(views, 1):
        camera = pycolmap.Camera(model="PINHOLE", width=1241, height=376, camera_id=index,
                                 params=[K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5])
        model.add_camera_with_trivial_rig(camera)
        image = pycolmap.Image(name=name, camera_id=index, image_id=index)
        model.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(pose[:3, :3]), pose[:3, 3]))
    folder.mkdir(parents=True)
    model.write_text(str(folder))
    return folder


def _edit_line(path: Path, first: str, fields: dict[int, str]) -> None:
    """Set fields (by index) of the data line of a COLMAP text file that starts with `first`."""
    lines = path.read_text().splitlines()
    for k, line in enumerate(lines):
        parts = line.split()
        if parts and not line.startswith("#") and parts[0] == first:
            for index, value in fields.items():
                parts[index] = value
            lines[k] = " ".join(parts)
            break
    else:
        raise AssertionError(f"{path}: no line {first}")
    path.write_text("\n".join(lines) + "\n")


def _sfm(shared_data, tmp_path, *source) -> str:
    return one_line_error(invoke("sfm", "--root", shared_data / KITTI, *source, "--matcher", "sift",
                                 "--out", tmp_path / "out"))


# frames.txt: FRAME_ID RIG_ID QW QX QY QZ TX TY TZ ...; cameras.txt: ID MODEL WIDTH HEIGHT fx fy cx cy
COLMAP_CASES = {
    "zero quaternion": ("frames.txt", {2: "0", 3: "0", 4: "0", 5: "0"}, "quaternion (0, 0, 0, 0) has norm 0, not 1"),
    "quaternion of norm 2": ("frames.txt", {2: "2", 3: "0", 4: "0", 5: "0"}, "has norm 2, not 1"),
    "focal -718": ("cameras.txt", {4: "-718"}, "focal length -718 is not positive"),
    "focal 0": ("cameras.txt", {5: "0"}, "focal length 0 is not positive"),
    "width 0": ("cameras.txt", {2: "0"}, "image size 0 x 376 is not positive"),
    "translation 1e9": ("frames.txt", {6: "1e9"}, "implausibly far"),
}


@pytest.mark.parametrize("case", COLMAP_CASES)
def test_colmap_model_with_bad_ground_truth_is_one_line(shared_data, tmp_path, case):
    """Before: a zero quaternion ran the whole benchmark on an identity pose (exit 0), a focal of
    -718 or 0 ran every pair to a failure; now each is refused before matching, naming the image."""
    _, views = _kitti(shared_data)
    model = _colmap_model(tmp_path / "model", views)
    file, fields, words = COLMAP_CASES[case]
    _edit_line(model / file, "2", fields)
    line = _sfm(shared_data, tmp_path, "--colmap-model", model)
    assert f"{model}: image {views[1][0]}: " in line and words in line
    assert not (tmp_path / "out" / "matches.h5").exists()


def _scene_info_with(tmp_path: Path, shared_data, index: int, K=None, pose=None) -> Path:
    scene = load_scene_info(shared_data / SCENE_INFO)
    paths = np.array(scene["image_paths"], dtype=object)
    paths[3:] = None
    intrinsics, poses = np.array(scene["intrinsics"], float), np.array(scene["poses"], float)
    if K is not None:
        intrinsics[index] = K
    if pose is not None:
        poses[index] = pose
    pair_infos = np.empty(2, dtype=object)
    pair_infos[0], pair_infos[1] = ((0, 1), 0.5, np.zeros(4)), ((1, 2), 0.5, np.zeros(4))
    out = tmp_path / "bad_scene.npz"
    np.savez(out, image_paths=paths, intrinsics=intrinsics, poses=poses, pair_infos=pair_infos)
    return out


def _bad_focal(K: np.ndarray) -> np.ndarray:
    K = np.array(K, float)
    K[0, 0] = -718
    return K


def test_the_same_focal_is_refused_in_the_same_words_from_every_source(shared_data, tmp_path):
    """A focal length of -718 from a COLMAP model, a scene_info (sfm and megadepth) and a pair
    list: one line each, naming the file, with the same words."""
    scene, views = _kitti(shared_data)
    model = _colmap_model(tmp_path / "model", views)
    _edit_line(model / "cameras.txt", "2", {4: "-718"})
    scene_info = _scene_info_with(tmp_path, shared_data, 1, K=_bad_focal(scene["intrinsics"][1]))
    pair_list = tmp_path / "pairs.txt"
    K0, K1, T = scene["intrinsics"][0], _bad_focal(scene["intrinsics"][1]), scene["poses"][1] @ np.linalg.inv(scene["poses"][0])
    pair_list.write_text(" ".join([views[0][0], views[1][0], "0", "0", *(repr(float(v)) for v in
                                   (*np.ravel(K0), *np.ravel(K1), *np.ravel(T)))]) + "\n")
    lines = {
        "colmap": _sfm(shared_data, tmp_path, "--colmap-model", model),
        "sfm scene_info": _sfm(shared_data, tmp_path, "--scene-info", scene_info),
        "sfm pair list": _sfm(shared_data, tmp_path, "--pairs", pair_list),
        "megadepth": one_line_error(invoke("megadepth", "--root", shared_data / KITTI, "--scene-info", scene_info,
                                           "--matcher", "sift", "--out", tmp_path / "md")),
        "yfcc": one_line_error(invoke("yfcc", "--root", shared_data / KITTI, "--pairs", pair_list,
                                      "--matcher", "sift", "--out", tmp_path / "yfcc")),
    }
    for source, line in lines.items():
        assert "focal length -718 is not positive" in line, source
    assert str(model) in lines["colmap"] and str(scene_info) in lines["megadepth"] and str(pair_list) in lines["yfcc"]


def test_scene_info_with_an_implausible_translation_is_one_line(shared_data, tmp_path):
    """A world-to-camera translation of 1e9 (a unit or parsing slip) is refused where it used to be
    read, by sfm (absolute poses) and megadepth (relative)."""
    scene = load_scene_info(shared_data / SCENE_INFO)
    pose = np.array(scene["poses"][1], float)
    pose[:3, 3] = [1e9, 0, 0]
    scene_info = _scene_info_with(tmp_path, shared_data, 1, pose=pose)
    assert "poses[1]" in _sfm(shared_data, tmp_path, "--scene-info", scene_info)
    line = one_line_error(invoke("megadepth", "--root", shared_data / KITTI, "--scene-info", scene_info,
                                 "--matcher", "sift", "--out", tmp_path / "md"))
    assert str(scene_info) in line and "poses[1]: the pose's translation has norm 1e+09, implausibly far" in line


def test_stereo_calibration_with_a_negative_focal_is_one_line(tmp_path):
    """KITTI's calib.txt with P0's fx negated (a left-handed camera): OpenCV's decomposition hands
    back negative focals; they were taken as the rig's ground truth, now `calibrate` refuses them."""
    import cv2

    root = tmp_path / "seq"
    for side in ("image_0", "image_1"):
        (root / side).mkdir(parents=True)
        for name in ("000000.png", "000001.png"):
            cv2.imwrite(str(root / side / name), np.full((48, 64, 3), 128, np.uint8))
    P0 = "-718.856 0 607.19 0 0 718.856 185.2 0 0 0 1 0"
    P1 = "718.856 0 607.19 -386.14 0 718.856 185.2 0 0 0 1 0"
    (root / "calib.txt").write_text(f"P0: {P0}\nP1: {P1}\n")
    line = one_line_error(invoke("calibrate", "--root", root, "--out", tmp_path / "out", "--matcher", "sift"))
    assert f"{root / 'calib.txt'}: the first projection matrix: focal length -718.856 is not positive" in line


def test_the_rule_itself():
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    check_intrinsics(K, "f")
    for bad, words in ((np.inf, "focal length inf is not finite"), (0.0, "focal length 0 is not positive")):
        K_bad = K.copy()
        K_bad[1, 1] = bad
        with pytest.raises(DatasetError, match=f"^f: {words}$"):
            check_intrinsics(K_bad, "f")
    K_bad = K.copy()
    K_bad[0, 2] = np.nan
    with pytest.raises(DatasetError, match="principal point"):
        check_intrinsics(K_bad, "f")
    check_quaternion([1, 1e-4, 0, 0], "f")  # rounding of a printed unit quaternion passes
    with pytest.raises(DatasetError, match=r"\(0, 0, 0, 0\) has norm 0"):
        check_quaternion([0, 0, 0, 0], "f")
    with pytest.raises(DatasetError, match="is not a rotation"):
        check_rotation(np.diag([1.0, 1, -1]), "f")  # a reflection: orthonormal, det -1
    T = np.eye(4)
    T[:3, 3] = [0, 0, 1e-12]
    with pytest.raises(DatasetError, match="no translation"):
        check_pose(T, "f")


def test_gluefactory_views_with_a_bad_pose_or_size_are_one_line(shared_data, tmp_path):
    """glue-factory's views.txt: a view whose R is no rotation, or whose image size is 0, is
    refused naming the file, the line and the view (with --skip-bad its pairs are skipped)."""
    from helpers import gluefactory_layout

    root = shared_data / KITTI
    folder = tmp_path / "megadepth1500"
    gluefactory_layout([shared_data / SCENE_INFO], folder, lambda rel, dest: dest.symlink_to(root / rel))
    original = (folder / "views.txt").read_text().splitlines()
    for edit, words in (({k: "0" for k in range(1, 10)}, "the pose's rotation is not a rotation"),
                        ({14: "0"}, "image size 0 x 8 is not positive")):
        lines = list(original)
        fields = lines[1].split()
        for k, value in edit.items():
            fields[k] = value
        lines[1] = " ".join(fields)
        (folder / "views.txt").write_text("\n".join(lines) + "\n")
        line = one_line_error(invoke("megadepth", "--root", folder, "--matcher", "sift", "--out", tmp_path / "out"))
        assert f"views.txt: line 2: view {fields[0]}: {words}" in line
