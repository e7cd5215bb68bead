"""Evaluation protocols (--protocol), upright matching of rotated pairs, EXIF orientation,
and the matcher settings the fidelity work added (--set)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import yaml

from e3cm_bench.geometry.metrics import summarize_pose
from e3cm_bench.pipeline.pair import match_pair, unrotate_points
from helpers import invoke, one_line_error

LITE = ["--backbone", "efficientnet_lite0"]


# --------------------------------------------------------------------------- rotations


@pytest.mark.parametrize("turns", [0, 1, 2, 3])
def test_unrotate_points_inverts_np_rot90(turns):
    rng = np.random.default_rng(turns)
    stored = rng.integers(0, 255, size=(7, 11), dtype=np.int64)  # h=7, w=11: not square
    rotated = np.rot90(stored, turns)
    ys, xs = np.mgrid[0 : rotated.shape[0], 0 : rotated.shape[1]]
    points = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float32)
    back = unrotate_points(points, turns, (11, 7)).astype(int)
    np.testing.assert_array_equal(stored[back[:, 1], back[:, 0]], rotated[ys.ravel(), xs.ravel()])


@pytest.fixture(scope="module")
def lite_matcher():
    from e3cm_bench.matchers import build_matcher

    return build_matcher("direct", "efficientnet_lite0")


def test_a_pair_stored_rotated_is_matched_upright_and_mapped_back(shared_data, lite_matcher):
    """Image B stored a quarter turn clockwise, with rot1 = 1 as a YFCC list would say: the
    matches equal those of the upright pair (B's keypoints mapped into the stored frame), and
    matching the stored images as they are finds far fewer correct ones (CNN features are not
    rotation invariant)."""
    from e3cm_bench.ground.images import load_image

    seq = shared_data / "hpatches-sequences-release" / "v_boat"
    image0 = cv2.resize(load_image(seq / "1.ppm"), None, fx=0.4, fy=0.4, interpolation=cv2.INTER_AREA)
    image1 = cv2.resize(load_image(seq / "2.ppm"), None, fx=0.4, fy=0.4, interpolation=cv2.INTER_AREA)
    stored1 = np.ascontiguousarray(np.rot90(image1, -1))
    upright = match_pair(lite_matcher, image0, image1)
    rotated = match_pair(lite_matcher, image0, stored1, rotations=(0, 1))
    assert len(rotated) == len(upright) > 50
    np.testing.assert_array_equal(rotated.keypoints0, upright.keypoints0)
    # Stored-frame keypoints of B, turned upright again: (x, y) -> (y, w_stored - 1 - x).
    w_stored = stored1.shape[1]
    again = np.stack([rotated.keypoints1[:, 1], w_stored - 1 - rotated.keypoints1[:, 0]], 1)
    np.testing.assert_allclose(again, upright.keypoints1, atol=1e-4)
    assert rotated.info["rotations"] == (0, 1)

    H = np.loadtxt(seq / "H_1_2")
    S = np.diag([0.4, 0.4, 1.0])
    H_small = S @ H @ np.linalg.inv(S)

    def correct(m, to_upright):
        k1 = to_upright(m.keypoints1)
        x = np.c_[m.keypoints0 + 0.5, np.ones(len(m))] @ H_small.T
        return np.sum(np.linalg.norm(x[:, :2] / x[:, 2:] - 0.5 - k1, axis=1) < 3)

    as_stored = match_pair(lite_matcher, image0, stored1)
    n_upright = correct(upright, lambda k: k)
    n_as_stored = correct(as_stored, lambda k: np.stack([k[:, 1], w_stored - 1 - k[:, 0]], 1))
    print(f"correct within 3 px: upright {n_upright}, as stored {n_as_stored}")
    assert n_as_stored < 0.5 * n_upright


def test_yfcc_pairs_carry_their_rotations_to_the_runner(tmp_path):
    from e3cm_bench.datasets.yfcc import YFCC100M
    from e3cm_bench.method.spec import MethodSpec
    from e3cm_bench.pipeline.pair import pair_rotations

    for name in ("a.jpg", "b.jpg"):
        cv2.imwrite(str(tmp_path / name), np.full((32, 48, 3), 128, np.uint8))
    K = "100 0 24 0 100 16 0 0 1"
    T = " ".join(map(str, [1, 0, 0, 0.5, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]))  # a pose needs a translation
    (tmp_path / "pairs.txt").write_text(f"a.jpg b.jpg 0 3 {K} {K} {T}\n")
    pair = next(iter(YFCC100M(tmp_path, pairs=tmp_path / "pairs.txt")))
    assert pair_rotations(pair, MethodSpec.create("sift")) == (0, 3)
    assert pair_rotations(pair, MethodSpec.create("sift", upright=False)) == (0, 0)
    assert MethodSpec.create("sift").identity()["upright"] is True


# --------------------------------------------------------------------------- EXIF


def test_jpeg_with_an_orientation_tag_is_read_turned_as_opencv_and_the_references_do(tmp_path):
    """The reference loaders (SuperGlue, LoFTR, the E3CM release) read with cv2.imread, which
    applies the EXIF orientation; so does load_image."""
    from PIL import Image

    from e3cm_bench.ground.images import load_image

    pixels = np.zeros((40, 60, 3), np.uint8)
    pixels[:10, :20] = (255, 0, 0)  # a red block top-left of the stored pixels
    exif = Image.Exif()
    exif[0x0112] = 6  # orientation 6: display turned 90 degrees clockwise
    path = tmp_path / "tagged.jpg"
    Image.fromarray(pixels).save(path, exif=exif.tobytes(), quality=95)

    image = load_image(path)
    assert image.shape == (60, 40, 3)  # turned: width and height swap
    expected = cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(image, expected)
    # Clockwise: the stored top-left block ends up top-right, and it is red.
    assert image[:20, -10:, 0].mean() > 200 and image[:20, -10:, 2].mean() < 60
    assert image[:20, :10, 0].mean() < 60


# --------------------------------------------------------------------------- failures in the AUC


def test_drop_failures_leaves_failed_pairs_out_of_the_auc():
    rows = [{"n_matches": 100, "err_pose": 1.0, "precision@1e-4": 1.0, "precision@5e-4": 1.0},
            {"n_matches": 3, "err_pose": math.inf, "precision@1e-4": 0.0, "precision@5e-4": 0.0}]
    counted = summarize_pose(rows)
    dropped = summarize_pose(rows, drop_failures=True)
    assert counted["n_failures"] == dropped["n_failures"] == 1
    assert counted["auc@5"] == pytest.approx(dropped["auc@5"] / 2)
    assert dropped["auc@5"] == pytest.approx(90.0)


# --------------------------------------------------------------------------- --protocol


def test_e3cm_release_protocol_is_written_and_flagged(shared_data, tmp_path):
    root = shared_data / "megadepth_test_1500"
    out = tmp_path / "rel"
    result = invoke("megadepth", "--root", root, "--scene-info", root / "scene_info" / "kitti00_seq.npz", "--out", out,
                    *LITE, "--matcher", "e3cm-release", "--protocol", "e3cm-release", "--limit", 1)
    assert result.exit_code == 0, result.output
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["evaluation"]["protocol"] == "e3cm-release" and config["evaluation"]["drop_failures"] is True
    identity = config["identity"]
    assert identity["max_side"] is None  # full resolution
    assert identity["settings"]["num_levels"] == 4 and identity["settings"]["channel_order"] == "bgr"
    assert config["matcher"]["num_levels"] == 4 and config["matcher"]["channel_order"] == "bgr"
    assert invoke("table", out, "--out", tmp_path / "t", "--no-compare").exit_code == 0
    table = (tmp_path / "t.md").read_text()
    assert "e3cm-release-efficientnet_lite0 (non-standard)" in table
    # Not VGG19: not comparable with the paper's E3CM row.
    assert "| E3CM " not in table.split("(non-standard)")[1]


def test_loftr_protocol_resizes_megadepth_to_840(shared_data, tmp_path):
    root = shared_data / "megadepth_test_1500"
    out = tmp_path / "loftr"
    result = invoke("megadepth", "--root", root, "--scene-info", root / "scene_info" / "kitti00_seq.npz", "--out", out,
                    "--matcher", "sift", "--protocol", "loftr", "--limit", 1)
    assert result.exit_code == 0, result.output
    assert "protocol loftr on megadepth: LoFTR's MegaDepth-1500 test config" in result.output  # said before the run
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["identity"]["max_side"] == 840 and config["evaluation"]["protocol"] == "loftr"
    # KITTI's 1241 x 376: 840 x round(254.5) = 255, each side floored to a multiple of 8 (LoFTR's df).
    from e3cm_bench.storage.cache import MatchCache

    assert config["identity"]["resize"] == "exact-div8"
    cache = MatchCache(out / "matches.h5")
    assert tuple(cache.read(cache.names()[0]).info["match_size0"]) == (840, 248)


@pytest.mark.parametrize("size", [(1296, 968), (1024, 683), (1241, 376), (376, 1241), (2000, 1500), (600, 1599)])
def test_resize_modes_give_the_reference_loaders_sizes_and_pixels(size):
    """exact = SuperGlue's process_resize (`--resize N`), exact-div8 = LoFTR's get_resized_wh then
    get_divisible_wh(df=8): the longer side scaled to N, enlarging too, Python's round; then
    cv2.resize with its default (bilinear) interpolation. shrink never enlarges."""
    from e3cm_bench.ground.images import resize_max_side

    w, h = size
    image = np.random.default_rng(0).integers(0, 256, (h, w, 3), dtype=np.uint8)
    for side in (840, 1600):
        scale = side / max(w, h)
        w_ref, h_ref = int(round(w * scale)), int(round(h * scale))
        for how, expected in (("exact", (w_ref, h_ref)), ("exact-div8", (w_ref // 8 * 8, h_ref // 8 * 8))):
            resized, scale_xy = resize_max_side(image, side, how)
            assert resized.shape[1::-1] == expected, (how, side)
            np.testing.assert_array_equal(resized, cv2.resize(image, expected))
            assert scale_xy == pytest.approx((w / expected[0], h / expected[1]))
        shrunk, _ = resize_max_side(image, side, "shrink")
        assert max(shrunk.shape[:2]) == min(side, max(w, h))
    with pytest.raises(ValueError, match="unknown resize"):
        resize_max_side(image, 840, "bicubic")


def test_superglue_protocol_enlarges_to_1600_as_its_eval_command(shared_data, tmp_path):
    """ScanNet's 1296 x 968 frames (YFCC pair-list format): the default shrinks them to 1200,
    `--protocol superglue` resizes them to 1600 x 1195, as match_pairs.py --resize 1600 does."""
    from e3cm_bench.storage.cache import MatchCache

    root = shared_data / "scannet_sample"
    sizes = {}
    for protocol in ("default", "superglue"):
        out = tmp_path / protocol
        result = invoke("yfcc", "--root", root, "--pairs", root / "pairs_with_gt.txt", "--out", out,
                        "--matcher", "sift", "--protocol", protocol, "--limit", 1)
        assert result.exit_code == 0, result.output
        config = yaml.safe_load((out / "config.yaml").read_text())
        cache = MatchCache(out / "matches.h5")
        sizes[protocol] = (config["identity"]["max_side"], config["identity"]["resize"],
                           tuple(cache.read(cache.names()[0]).info["match_size0"]),
                           config["evaluation"]["pose_ransac_px"], config["evaluation"]["pose_ransac_frame"])
    assert sizes["default"] == (1200, "shrink", (1200, 896), 0.5, "original")
    assert sizes["superglue"] == (1600, "exact", (1600, 1195), 1.0, "matched")


def test_a_ransac_threshold_in_matched_pixels_is_superglues_normalised_threshold():
    """SuperGlue: 1 px / mean focal of K scaled to the resized image. Ours: the threshold in stored
    pixels over the stored K's mean focal; the two normalised thresholds must agree."""
    from e3cm_bench.benchmarks import get_benchmark
    from e3cm_bench.benchmarks.eval_settings import EvalSettings
    from e3cm_bench.datasets.base import Pair
    from e3cm_bench.ground.matches import Matches

    K0 = np.array([[1065.0, 0, 512], [0, 1065.0, 384], [0, 0, 1]])
    K1 = np.array([[900.0, 0, 400], [0, 900.0, 300], [0, 0, 1]])
    pair = Pair("p", None, None, K0=K0, K1=K1, T_0to1=np.eye(4))
    # Image 0 stored 1024 x 768, matched at 1600 x 1200; image 1 stored upright-rotated 600 x 800,
    # matched at 1200 x 1600.
    info = {"size0": (1024, 768), "match_size0": (1600, 1200), "size1": (600, 800), "match_size1": (1200, 1600)}
    matches = Matches(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), info)
    pose = get_benchmark("yfcc")
    ev = EvalSettings(pose_ransac_px=1.0, pose_ransac_frame="matched")
    ours = pose.ransac_px(pair, matches, ev) / np.mean([K0[0, 0], K0[1, 1], K1[0, 0], K1[1, 1]])
    K0_resized, K1_resized = K0[0, 0] * 1600 / 1024, K1[0, 0] * 1600 / 800
    assert ours == pytest.approx(1.0 / np.mean([K0_resized, K1_resized]))
    assert pose.ransac_px(pair, matches, EvalSettings(pose_ransac_px=0.5)) == 0.5


def test_a_run_written_before_resize_modes_resumes(shared_data, tmp_path):
    root = shared_data / "scannet_sample"
    args = ("yfcc", "--root", root, "--pairs", root / "pairs_with_gt.txt", "--out", tmp_path / "old", "--matcher", "sift")
    assert invoke(*args, "--limit", 1).exit_code == 0
    config_path = tmp_path / "old" / "config.yaml"
    config = yaml.safe_load(config_path.read_text())
    del config["identity"]["resize"]  # as an older e3cm-bench wrote it
    config_path.write_text(yaml.safe_dump(config))
    result = invoke(*args, "--limit", 1)
    assert result.exit_code == 0 and "all 1 pairs found" in result.output, result.output
    refused = invoke(*args, "--limit", 1, "--protocol", "superglue")
    assert refused.exit_code != 0 and "resize" in refused.output


def test_a_protocol_of_another_benchmark_is_a_one_line_error(tmp_path):
    line = one_line_error(invoke("hpatches", "--root", tmp_path, "--out", tmp_path / "o", "--protocol", "superglue"))
    assert "superglue" in line and "yfcc" in line
    line = one_line_error(invoke("hpatches", "--root", tmp_path, "--out", tmp_path / "o", "--protocol", "nope"))
    assert "unknown protocol" in line


def test_the_default_protocol_holds_for_a_benchmark_added_later():
    """A new benchmark module needs no line in protocols.py: `default` sets nothing of its own."""
    from e3cm_bench.benchmarks import HomographyBenchmark
    from e3cm_bench.method.protocols import get_protocol
    from e3cm_bench.datasets.hpatches import HPatches

    assert get_protocol("default", "added-later").name == "default"
    spec = HomographyBenchmark(name="added-later", dataset=HPatches).resolve_method("sift")
    assert spec.matcher == "sift" and spec.max_side is None
    with pytest.raises(ValueError, match="defined for"):
        get_protocol("wxbs", "added-later")


def test_set_rejects_a_setting_the_matcher_does_not_have(tmp_path):
    line = one_line_error(invoke("hpatches", "--root", tmp_path, "--out", tmp_path / "o", "--matcher", "e3cm",
                                 "--set", "variant=corrected"))
    assert "variant" in line
    line = one_line_error(invoke("hpatches", "--root", tmp_path, "--out", tmp_path / "o", "--matcher", "dfm",
                                 "--set", "variant=newest"))
    assert "release, corrected, bench" in line
    line = one_line_error(invoke("hpatches", "--root", tmp_path, "--out", tmp_path / "o", "--set", "nokey"))
    assert "KEY=VALUE" in line


# --------------------------------------------------------------------------- precision


def test_bf16_backbone_is_recorded_and_stays_close_to_fp32(shared_data):
    """--precision bf16 runs the backbone under autocast (channels_last); it is part of the
    match identity. On v_boat 1-2 at 480 px its matches stay about as correct as fp32's."""
    import torch

    from e3cm_bench.ground.images import load_image
    from e3cm_bench.method.spec import MethodSpec

    if not hasattr(torch.backends, "mkldnn") or not torch.backends.mkldnn.is_available():
        pytest.skip("no oneDNN CPU backend for bf16 here")
    spec = MethodSpec.create("direct", "efficientnet_lite0", options={"precision": "bf16"})
    assert spec.identity()["settings"]["precision"] == "bf16"
    assert spec != MethodSpec.create("direct", "efficientnet_lite0")
    seq = shared_data / "hpatches-sequences-release" / "v_boat"
    image0, image1 = load_image(seq / "1.ppm"), load_image(seq / "2.ppm")
    H = np.loadtxt(seq / "H_1_2")
    fractions = {}
    for precision in ("fp32", "bf16"):
        matcher = MethodSpec.create("direct", "efficientnet_lite0", options={"precision": precision}).build()
        assert matcher.config()["precision"] == precision
        m = match_pair(matcher, image0, image1, max_side=480)
        x = np.c_[m.keypoints0 + 0.5, np.ones(len(m))] @ H.T
        err = np.linalg.norm(x[:, :2] / x[:, 2:] - 0.5 - m.keypoints1, axis=1)
        fractions[precision] = (len(m), float(np.mean(err < 3 * image0.shape[1] / 480)))
    print("matches, fraction within 3 px (at 480 px):", fractions)
    (n32, f32), (n16, f16) = fractions["fp32"], fractions["bf16"]
    assert abs(n16 - n32) <= 0.15 * n32 and f16 >= f32 - 0.05


# --------------------------------------------------------------------------- feature reuse


def test_channel_order_option_reaches_the_identity(shared_data, tmp_path):
    root = shared_data / "hpatches-sequences-release"
    out = tmp_path / "bgr"
    result = invoke("hpatches", "--root", root, "--out", out, *LITE, "--matcher", "direct", "--channel-order", "bgr",
                    "--sequences", "v_boat", "--limit", 1, "--max-side", 320)
    assert result.exit_code == 0, result.output
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["identity"]["settings"]["channel_order"] == "bgr" and config["matcher"]["channel_order"] == "bgr"
