"""Dataset loaders on the real samples in ../shared/data, and on malformed inputs built here."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from e3cm_bench.benchmarks import BENCHMARKS
from e3cm_bench.datasets import DatasetError, HPatches, MegaDepth1500, YFCC100M
from e3cm_bench.geometry.two_view import warp_points
from e3cm_bench.geometry.metrics import evaluate_pose_pair
from helpers import gluefactory_layout


def touch(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"P6 1 1 255\n\x00\x00\x00")  # a 1 x 1 image: present and whole
    return path


def test_registry_names():
    from e3cm_bench.benchmarks.evd import EVD
    from e3cm_bench.benchmarks.wxbs import WxBS
    from e3cm_bench.sfm.dataset import MultiViewSet

    assert {name: b.dataset for name, b in BENCHMARKS.items()} == {
        "hpatches": HPatches, "megadepth": MegaDepth1500, "yfcc": YFCC100M, "wxbs": WxBS, "evd": EVD,
        "sfm": MultiViewSet}
    assert list(BENCHMARKS)[:3] == ["hpatches", "megadepth", "yfcc"]  # the paper's first (commands, --help)


# --------------------------------------------------------------------------- HPatches


@pytest.fixture(scope="module")
def hpatches_root(shared_data: Path) -> Path:
    return shared_data / "hpatches-sequences-release"


def test_hpatches_pairs_names_and_ground_truth(hpatches_root: Path):
    dataset = HPatches(hpatches_root)
    pairs = list(dataset)
    assert len(dataset) == len(pairs) == 15
    expected_names = [f"i_leuven/1-{k}" for k in range(2, 7)] + ["v_boat/1-2"]
    assert [p.name for p in pairs[:6]] == expected_names
    boat = pairs[5]
    assert boat.image0 == hpatches_root / "v_boat" / "1.ppm"
    assert boat.image1 == hpatches_root / "v_boat" / "2.ppm"
    assert boat.sequence == "v_boat" and boat.labels == {"sequence": "v_boat"}
    assert pairs[0].labels == {"sequence": "i_leuven"}
    np.testing.assert_array_equal(boat.H, np.loadtxt(hpatches_root / "v_boat" / "H_1_2"))
    # The centre of image 1 lands inside image 2.
    height0, width0 = cv2.imread(str(boat.image0), cv2.IMREAD_GRAYSCALE).shape
    height1, width1 = cv2.imread(str(boat.image1), cv2.IMREAD_GRAYSCALE).shape
    x, y = warp_points(boat.H, np.array([[width0 / 2, height0 / 2]]))[0]
    assert 0 <= x < width1 and 0 <= y < height1
    assert dataset.describe()["n_pairs"] == 15 and "580" in dataset.describe()["protocol"]


def test_hpatches_sequence_filter(hpatches_root: Path):
    viewpoint = HPatches(hpatches_root, sequences=["v_*"])
    assert len(viewpoint) == 10
    assert {p.sequence[:2] for p in viewpoint} == {"v_"}
    assert len(HPatches(hpatches_root, sequences=["i_leuven", "v_boat"])) == 10
    assert len(HPatches(hpatches_root, sequences="v_boat")) == 5
    with pytest.raises(DatasetError, match="v_nothing"):
        HPatches(hpatches_root, sequences=["v_nothing*"])


def test_hpatches_exclude_large_protocol(hpatches_root: Path):
    dataset = HPatches(hpatches_root, exclude_large=True)
    assert len(dataset) == 15  # none of the 8 large sequences is in the sample
    description = dataset.describe()
    assert "540" in description["protocol"] and "108" in description["protocol"]
    assert description["sequences"] == ["i_leuven", "v_boat", "v_graffiti"]


def make_hpatches_sequence(root: Path, name: str = "v_fake") -> Path:
    folder = root / name
    for k in range(1, 7):
        touch(folder / f"{k}.ppm")
    for k in range(2, 7):
        np.savetxt(folder / f"H_1_{k}", np.eye(3))
    return folder


def test_hpatches_missing_homography_file(tmp_path: Path):
    folder = make_hpatches_sequence(tmp_path)
    (folder / "H_1_3").unlink()
    with pytest.raises(DatasetError, match="H_1_3"):
        HPatches(tmp_path)


def test_hpatches_malformed_homography_file(tmp_path: Path):
    folder = make_hpatches_sequence(tmp_path)
    (folder / "H_1_4").write_text("1 0 0\n0 1 0\n")
    with pytest.raises(DatasetError, match="H_1_4") as error:
        HPatches(tmp_path)
    assert "\n" not in str(error.value)


def test_hpatches_missing_images_and_skip(tmp_path: Path):
    make_hpatches_sequence(tmp_path, "v_fake")
    folder = make_hpatches_sequence(tmp_path, "i_fake")
    (folder / "5.ppm").unlink()
    with pytest.raises(DatasetError, match=r"1 image\(s\) missing.*5\.ppm.*--skip-bad"):
        HPatches(tmp_path)
    dataset = HPatches(tmp_path, skip_bad=True)
    assert len(dataset) == 9 and dataset.n_skipped == 1
    assert "i_fake/1-5" not in [p.name for p in dataset]
    assert dataset.describe()["n_skipped"] == 1


def test_hpatches_missing_root(tmp_path: Path):
    with pytest.raises(DatasetError, match="nowhere"):
        HPatches(tmp_path / "nowhere")


# --------------------------------------------------------------------------- MegaDepth-1500


@pytest.fixture(scope="module")
def megadepth_root(shared_data: Path) -> Path:
    return shared_data / "megadepth_test_1500"


def assert_rigid(T: np.ndarray, atol: float = 1e-6) -> None:
    assert T.shape == (4, 4)
    np.testing.assert_allclose(T[3], [0, 0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=atol)
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0, abs=atol)


def kitti(megadepth_root: Path) -> MegaDepth1500:
    """The 31 real KITTI pairs, the only list here whose images are all present."""
    scene_info = megadepth_root / "scene_info" / "kitti00_seq.npz"
    return MegaDepth1500(megadepth_root, scene_info=[scene_info])


def test_megadepth_kitti_pairs(megadepth_root: Path):
    dataset = kitti(megadepth_root)
    assert len(dataset) == 31
    first = dataset[0]
    assert first.name == "kitti00_seq/000100--000103"
    assert first.image0 == megadepth_root / "Undistorted_SfM" / "kitti00" / "images" / "000100.png"
    assert first.labels == {"scene": "kitti00_seq"}
    assert first.K0.shape == first.K1.shape == (3, 3)
    for pair in dataset:
        assert_rigid(pair.T_0to1)
    assert dataset.describe()["n_pairs"] == 31


def test_megadepth_default_lists_need_their_images(megadepth_root: Path):
    with pytest.raises(DatasetError) as error:
        MegaDepth1500(megadepth_root)
    message = str(error.value)
    count = re.search(r"(\d+) image\(s\) missing", message)
    assert count and int(count.group(1)) > 0
    assert "Undistorted_SfM/00" in message and "--skip-bad" in message


def test_megadepth_skip_bad_keeps_complete_pairs(megadepth_root: Path):
    dataset = MegaDepth1500(megadepth_root, skip_bad=True)
    # No pair of the 5 real lists (1500 pairs) has both images present; the KITTI ones do.
    assert len(dataset) == 31
    assert all(p.name.startswith("kitti00_seq/") for p in dataset)
    assert dataset.n_skipped == 1500
    description = dataset.describe()
    assert description["n_skipped"] == 1500 and len(description["scene_info"]) == 6


def test_megadepth_unreadable_scene_info(tmp_path: Path):
    bad = tmp_path / "scene_info" / "bad.npz"
    bad.parent.mkdir()
    bad.write_text("not an archive")
    with pytest.raises(DatasetError, match="bad.npz"):
        MegaDepth1500(tmp_path)


def test_megadepth_scene_info_without_poses(tmp_path: Path):
    path = tmp_path / "partial.npz"
    image_paths = np.array(["a.png", "b.png"], dtype=object)
    np.savez(path, image_paths=image_paths, intrinsics=np.zeros((2, 3, 3)))
    with pytest.raises(DatasetError, match="partial.npz.*poses"):
        MegaDepth1500(tmp_path, scene_info=[path])


def test_megadepth_pair_on_an_unused_image(tmp_path: Path):
    path = tmp_path / "holes.npz"
    pair_infos = np.empty(1, dtype=object)
    pair_infos[0] = ((0, 1), 0.5, np.zeros(4))
    np.savez(
        path,
        image_paths=np.array(["a.png", None], dtype=object),
        intrinsics=np.stack([np.eye(3)] * 2),
        poses=np.stack([np.eye(4)] * 2),
        pair_infos=pair_infos,
    )
    with pytest.raises(DatasetError, match=r"holes.npz.*pair_infos\[0\].*image 1"):
        MegaDepth1500(tmp_path, scene_info=[path])


def sift_matches(image0: Path, image1: Path, ratio: float = 0.8) -> tuple[np.ndarray, np.ndarray]:
    sift = cv2.SIFT_create()
    gray0 = cv2.imread(str(image0), cv2.IMREAD_GRAYSCALE)
    gray1 = cv2.imread(str(image1), cv2.IMREAD_GRAYSCALE)
    keypoints0, descriptors0 = sift.detectAndCompute(gray0, None)
    keypoints1, descriptors1 = sift.detectAndCompute(gray1, None)
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(descriptors0, descriptors1, k=2)
    good = [m for m, n in pairs if m.distance < ratio * n.distance]
    return (
        np.array([keypoints0[m.queryIdx].pt for m in good]),
        np.array([keypoints1[m.trainIdx].pt for m in good]),
    )


def test_kitti_ground_truth_agrees_with_sift(megadepth_root: Path):
    """End to end on real images: T_0to1 direction, K and the pose metric agree with SIFT."""
    errors, errors_if_inverted = [], []
    for pair in list(kitti(megadepth_root))[:4]:
        kpts0, kpts1 = sift_matches(pair.image0, pair.image1)
        for T, found in ((pair.T_0to1, errors), (np.linalg.inv(pair.T_0to1), errors_if_inverted)):
            found.append(evaluate_pose_pair(kpts0, kpts1, pair.K0, pair.K1, T, seed=0)["err_pose"])
    assert sum(e < 5.0 for e in errors) >= 3, errors
    # The opposite convention (poses[i] @ inv(poses[j])) is off by far more (~17 deg here).
    assert all(bad > 3 * good for good, bad in zip(errors, errors_if_inverted)), errors_if_inverted


def tiny_image(relative: str, destination: Path) -> None:
    destination.parent.mkdir(parents=True, exist_ok=True)
    if not destination.exists():
        cv2.imwrite(str(destination), np.zeros((4, 4), np.uint8))


def test_megadepth_both_layouts_give_the_same_1500_pairs_in_the_same_order(megadepth_root: Path, tmp_path: Path):
    """The real LoFTR lists, and the same numbers written in glue-factory's layout: one reader each,
    the same pairs (images, K, T_0to1) in the same order. Images are stand-ins (the pairs' ground truth is real)."""
    scene_infos = [megadepth_root / "scene_info" / f"{s}.npz" for s in
                   ("0015_0.1_0.3", "0015_0.3_0.5", "0022_0.1_0.3", "0022_0.3_0.5", "0022_0.5_0.7")]
    loftr = tmp_path / "megadepth_test_1500"
    (loftr / "scene_info").mkdir(parents=True)
    for path in scene_infos:
        (loftr / "scene_info" / path.name).symlink_to(path)
    n = gluefactory_layout(scene_infos, tmp_path / "megadepth1500",
                           lambda relative, destination: (tiny_image(relative, loftr / relative),
                                                          tiny_image(relative, destination)))
    assert n == 1500
    a = MegaDepth1500(loftr)
    b = MegaDepth1500(tmp_path)  # the folder that holds megadepth1500/, as glue-factory unpacks it
    assert (a.layout, b.layout) == ("loftr", "gluefactory") and len(a) == len(b) == 1500
    assert b.settings()["views"] == str(tmp_path / "megadepth1500" / "views.txt")
    for pa, pb in zip(a, b):
        assert (pa.image0.name, pa.image1.name) == (pb.image0.name, pb.image1.name)
        assert pb.name == f"megadepth1500/{pa.image0.stem}--{pa.image1.stem}"
        np.testing.assert_array_equal(pa.K0, pb.K0)
        np.testing.assert_array_equal(pa.K1, pb.K1)
        np.testing.assert_allclose(pa.T_0to1, pb.T_0to1, rtol=0, atol=1e-12)


def write_views(folder: Path, lines: list[str], pairs: list[str]) -> Path:
    (folder / "images").mkdir(parents=True, exist_ok=True)
    for name in ("a.jpg", "b.jpg", "c.jpg"):
        tiny_image(name, folder / "images" / name)
    (folder / "views.txt").write_text("\n".join(lines) + "\n")
    (folder / "pairs.txt").write_text("\n".join(pairs) + "\n")
    return folder


POSE = "1 0 0 0 1 0 0 0 1 0 0 0"
MOVED = "1 0 0 0 1 0 0 0 1 1 0 0"


def test_gluefactory_layout_bad_input_is_one_line_naming_the_file(tmp_path: Path):
    good = [f"a.jpg {POSE} PINHOLE 8 8 500 500 4 4", f"b.jpg {MOVED} SIMPLE_PINHOLE 8 8 500 4 4"]
    dataset = MegaDepth1500(write_views(tmp_path / "ok", good, ["a.jpg b.jpg"]))
    np.testing.assert_array_equal(dataset[0].K1, [[500, 0, 4], [0, 500, 4], [0, 0, 1]])
    np.testing.assert_allclose(dataset[0].T_0to1[:3, 3], [1, 0, 0])
    cases = [
        (good, ["a.jpg b.jpg c.jpg"], r"pairs\.txt: line 1 holds 3 names, not two"),
        (good, ["a.jpg c.jpg"], r"pairs\.txt: line 1 names c\.jpg, which views\.txt does not list"),
        ([f"a.jpg {POSE} PINHOLE 8"], ["a.jpg a.jpg"], r"views\.txt: line 1 holds 15 fields"),
        ([f"a.jpg {POSE} PINHOLE 8 8 500 x 4 4"], ["a.jpg a.jpg"], r"views\.txt: line 1: a pose or camera value is not a number"),
        (good + [good[0]], ["a.jpg b.jpg"], r"views\.txt: line 3: view a\.jpg is listed twice"),
        # the line number an editor shows: comments and blank lines above count
        (good, ["# the pairs", "", "a.jpg c.jpg"], r"pairs\.txt: line 3 names c\.jpg"),
        (["# K, R, t", *good, "  # an indented comment"], ["a.jpg b.jpg b.jpg"], r"pairs\.txt: line 1 holds 3"),
    ]
    for number, (views, pairs, says) in enumerate(cases):
        with pytest.raises(DatasetError, match=says):
            MegaDepth1500(write_views(tmp_path / str(number), views, pairs))
    # a camera K cannot describe is a bad pair: refused, or skipped with --skip-bad
    distorted = good + [f"c.jpg {MOVED} OPENCV 8 8 500 500 4 4 0.1 0 0 0"]
    folder = write_views(tmp_path / "distorted", distorted, ["a.jpg b.jpg", "a.jpg c.jpg"])
    with pytest.raises(DatasetError, match=r"views\.txt: line 3: camera OPENCV has non-zero distortion"):
        MegaDepth1500(folder)
    assert [p.name for p in MegaDepth1500(folder, skip_bad=True)] == ["megadepth1500/a--b"]
    with pytest.raises(DatasetError, match=r"holds neither scene_info/\*\.npz .* nor views\.txt and pairs\.txt"):
        MegaDepth1500(tmp_path / "ok" / "images")


# --------------------------------------------------------------------------- YFCC100M / ScanNet


def test_scannet_sample_list(shared_data: Path):
    root = shared_data / "scannet_sample"
    dataset = YFCC100M(root, pairs=root / "pairs_with_gt.txt")
    assert len(dataset) == 8
    first = dataset[0]
    assert first.name == "scene0711_00_frame-001680--scene0711_00_frame-001995"
    assert first.image0 == root / "images" / "scene0711_00_frame-001680.jpg"
    assert first.labels == {} and first.rotations == (0, 0)
    assert first.K0[0, 0] == pytest.approx(1163.45) and first.K0[1, 2] == pytest.approx(481.6)
    for pair in dataset:
        assert_rigid(pair.T_0to1, atol=1e-4)  # the list prints rotations to 5 decimals
    assert dataset.describe()["pairs"] == str(root / "pairs_with_gt.txt")


def test_yfcc_real_list_without_images(shared_data: Path):
    with pytest.raises(DatasetError) as error:
        YFCC100M(shared_data)
    message = str(error.value)
    assert "yfcc_test_pairs_with_gt.txt" in message
    assert "buckingham_palace/test/images/" in message and "--skip-bad" in message


def write_pair_list(path: Path, lines: list[str]) -> Path:
    path.write_text("\n".join(lines) + "\n")
    return path


def pair_line(name0: str, name1: str, rot0: int = 0, rot1: int = 0) -> str:
    K = "500 0 320 0 500 240 0 0 1"
    T = "1 0 0 0.5 0 1 0 0 0 0 1 0 0 0 0 1"
    return f"{name0} {name1} {rot0} {rot1} {K} {K} {T}"


def test_yfcc_names_with_folders(tmp_path: Path):
    touch(tmp_path / "sceneA" / "images" / "a.jpg")
    touch(tmp_path / "sceneA" / "images" / "b.jpg")
    line = pair_line("sceneA/images/a.jpg", "sceneA/images/b.jpg", rot0=0, rot1=1)
    pairs = write_pair_list(tmp_path / "pairs.txt", [line])
    pair = YFCC100M(tmp_path, pairs=pairs)[0]
    assert pair.name == "sceneA/images/a--b"
    assert pair.labels == {"scene": "sceneA"} and pair.rotations == (0, 1)
    assert pair.T_0to1[0, 3] == 0.5


def test_yfcc_line_with_missing_fields(tmp_path: Path):
    touch(tmp_path / "a.jpg")
    lines = [pair_line("a.jpg", "a2.jpg"), "a.jpg b.jpg 0 0 1 2 3"]
    pairs = write_pair_list(tmp_path / "pairs.txt", lines)
    with pytest.raises(DatasetError, match=r"pairs\.txt:2: expected 38 fields, found 7"):
        YFCC100M(tmp_path, pairs=pairs)


def test_yfcc_non_numeric_and_bad_rotation(tmp_path: Path):
    word_for_number = pair_line("a.jpg", "b.jpg").replace("500", "five", 1)
    bad_number = write_pair_list(tmp_path / "nan.txt", [word_for_number])
    with pytest.raises(DatasetError, match=r"nan\.txt:1: not a number"):
        YFCC100M(tmp_path, pairs=bad_number)
    bad_rotation = write_pair_list(tmp_path / "rot.txt", [pair_line("a.jpg", "b.jpg", 5, 0)])
    with pytest.raises(DatasetError, match=r"rot\.txt:1: .*rotation"):
        YFCC100M(tmp_path, pairs=bad_rotation)


def test_yfcc_empty_and_duplicate_lists(tmp_path: Path):
    touch(tmp_path / "a.jpg")
    touch(tmp_path / "b.jpg")
    with pytest.raises(DatasetError, match=r"empty\.txt: the pair list is empty"):
        YFCC100M(tmp_path, pairs=write_pair_list(tmp_path / "empty.txt", [""]))
    twice = write_pair_list(tmp_path / "twice.txt", [pair_line("a.jpg", "b.jpg")] * 2)
    with pytest.raises(DatasetError, match=r"twice\.txt: pair name 'a--b' occurs twice"):
        YFCC100M(tmp_path, pairs=twice)
    with pytest.raises(DatasetError, match="absent.txt"):
        YFCC100M(tmp_path, pairs=tmp_path / "absent.txt")


def test_a_pair_list_is_read_in_one_place_with_its_file_line_numbers(tmp_path: Path):
    """datasets.base.name_pairs: MegaDepth's pairs.txt and the sfm pair graph read through it."""
    from e3cm_bench.datasets.base import name_pairs

    path = tmp_path / "pairs.txt"
    path.write_text("# header\n\na b\n   # note\nb c\n")
    assert list(name_pairs(path, {"a", "b", "c"}, "unknown")) == [(3, "a", "b"), (5, "b", "c")]
    path.write_text("# header\na b\nb x\n")
    with pytest.raises(DatasetError, match=r"pairs\.txt: line 3 names x, which is not here"):
        list(name_pairs(path, {"a", "b"}, "which is not here"))
    path.write_bytes(b"\xff\xfe a b\n")
    with pytest.raises(DatasetError, match=r"pairs\.txt: not readable"):
        list(name_pairs(path, {"a", "b"}, "unknown"))
