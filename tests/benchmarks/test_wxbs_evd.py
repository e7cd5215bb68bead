"""WxBS and EVD: loaders on the shared data, bad input, the metrics, and parity with the
reference evaluator (the `wxbs-benchmark` package) on every shared pair."""

from __future__ import annotations

import numpy as np
import pytest

from e3cm_bench.benchmarks import get_benchmark
from e3cm_bench.benchmarks import evd as evd_module
from e3cm_bench.benchmarks import wxbs as wxbs_module
from e3cm_bench.benchmarks.eval_settings import EvalSettings
from e3cm_bench.method.protocols import get_protocol
from e3cm_bench.datasets.base import DatasetError
from e3cm_bench.geometry.estimators import fundamental, homography
from e3cm_bench.geometry.two_view import warp_points
from e3cm_bench.ground.matches import Matches


# ----------------------------------------------------------------------------- loaders


def test_wxbs_splits_on_the_shared_data(wxbs_root):
    bench = get_benchmark("wxbs")
    test = bench.load_dataset(wxbs_root)  # the default split is the test set
    val = bench.load_dataset(wxbs_root, split="val")
    both = bench.load_dataset(wxbs_root, split="all")
    assert (len(test), len(val), len(both)) == (31, 2, 33)
    assert [p.name for p in val] == ["WGABS/petrzin", "WGALBS/kyiv_dolltheater2"]
    assert {p.name for p in test} | {p.name for p in val} == {p.name for p in both}
    assert {p.category for p in both} == {"WGABS", "WGALBS", "WGBS", "WGLBS", "WGSBS", "WLABS"}
    thermal = next(p for p in both if p.name == "WGSBS/kettle")
    assert thermal.corrs.shape[1] == 4 and len(thermal.corrs) >= 8
    # the root may be the version folder itself
    assert len(bench.load_dataset(wxbs_root / "v1.1")) == 31
    with pytest.raises(DatasetError, match="split must be one of"):
        bench.load_dataset(wxbs_root, split="train")


def test_evd_on_the_shared_data(evd_root):
    pairs = get_benchmark("evd").load_dataset(evd_root)
    assert len(pairs) == 15
    fox = next(p for p in pairs if p.name == "fox")
    assert fox.image0.parent.name == "1" and fox.image1.parent.name == "2"
    assert fox.H.shape == (3, 3) and fox.H[2, 2] == 1.0
    # the shared copy is the complete release, in the layout `download evd` places
    from e3cm_bench.data import download
    from e3cm_bench.datasets.sources import get_source

    assert "complete (15 pairs)" in download.check(get_source("evd"), evd_root.parent)


def test_the_shared_wxbs_copy_is_the_release_layout_short_of_one_test_pair(wxbs_root):
    from e3cm_bench.data import download
    from e3cm_bench.datasets.sources import get_source

    # ../shared/data lacks WLABS/ministry (its first image is missing from the copy reachable here)
    with pytest.raises(download.DownloadError, match="pairs 31 of 32"):
        download.check(get_source("wxbs"), wxbs_root.parent)


def _wxbs_pair(root, name="cat/pair", corrs="1 2 3 4\n5 6 7 8\n", images=("01.png", "02.png")):
    folder = root / name
    folder.mkdir(parents=True)
    (folder / "corrs.txt").write_text(corrs)
    for image in images:
        (folder / image).write_bytes(_PNG)
    return folder


# The smallest valid PNG (1 x 1 grey): the loader's image check reads its signature and IEND.
_PNG = bytes.fromhex(
    "89504e470d0a1a0a0000000d4948445200000001000000010800000000"
    "3a7e9b550000000a49444154789c63600000000200015d1f3d2b0000000049454e44ae426082"
)


def test_wxbs_corrs_with_three_columns_is_one_line_naming_the_file(tmp_path):
    folder = _wxbs_pair(tmp_path / "v1.1", corrs="1 2 3\n4 5 6\n")
    with pytest.raises(DatasetError) as error:
        get_benchmark("wxbs").load_dataset(tmp_path)
    message = str(error.value)
    assert "\n" not in message and str(folder / "corrs.txt") in message and "4 columns" in message


def test_wxbs_missing_image_is_one_line_naming_the_file(tmp_path):
    folder = _wxbs_pair(tmp_path / "v1.1", images=("02.jpg",))
    with pytest.raises(DatasetError) as error:
        get_benchmark("wxbs").load_dataset(tmp_path)
    message = str(error.value)
    # the missing first image is named with the suffix its partner has
    assert "\n" not in message and str(folder / "01.jpg") in message and "missing" in message


def _evd_pair(root, name="fox", H="1 0 0\n0 1 0\n0 0 1\n", images=("1", "2")):
    for sub in ("1", "2", "h"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    for sub in images:
        (root / sub / f"{name}.png").write_bytes(_PNG)
    (root / "h" / f"{name}.txt").write_text(H)


def test_evd_h_that_is_not_3x3_is_one_line_naming_the_file(tmp_path):
    _evd_pair(tmp_path, H="1 0 0\n0 1 0\n")
    with pytest.raises(DatasetError) as error:
        get_benchmark("evd").load_dataset(tmp_path)
    message = str(error.value)
    assert "\n" not in message and str(tmp_path / "h" / "fox.txt") in message and "3x3" in message


def test_evd_missing_image_is_one_line_naming_the_file(tmp_path):
    _evd_pair(tmp_path, name="fox", images=("1",))
    _evd_pair(tmp_path, name="cat")
    with pytest.raises(DatasetError) as error:
        get_benchmark("evd").load_dataset(tmp_path)
    message = str(error.value)
    assert "\n" not in message and str(tmp_path / "2" / "fox.png") in message
    # --skip-bad evaluates the sound pair and lists the other
    kept = get_benchmark("evd").load_dataset(tmp_path, skip_bad=True)
    assert [p.name for p in kept] == ["cat"] and kept.n_skipped == 1


# ----------------------------------------------------------------------------- metrics


def test_symmetric_epipolar_distance_of_a_known_geometry():
    # A pure horizontal translation: F = [t]_x with t = (1, 0, 0); epipolar lines are rows, so
    # a point's distance to the other's line is the difference of their y, in both images.
    F = np.array([[0, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=np.float64)
    x0 = np.array([[10.0, 20.0], [5.0, 7.0]])
    x1 = np.array([[40.0, 23.0], [9.0, 7.0]])
    d = wxbs_module.symmetric_epipolar_distance(F, x0, x1)
    # residual r = y0 - y1 (or its negative); d^2 = r^2 (1 + 1) -> d = sqrt(2) |r|
    assert np.allclose(d, [3 * np.sqrt(2), 0.0])
    curve = wxbs_module.recall_curve(F, np.hstack([x0, x1]))
    assert curve[0] == 0.5 and curve[4] == 0.5 and curve[5] == 1.0
    assert wxbs_module.recall_curve(None, np.hstack([x0, x1])).sum() == 0  # no F: nothing recalled
    # mAA@10px is the mean at 1..10 px, not at 0..9
    assert wxbs_module.maa(np.arange(20) / 20) == pytest.approx(np.mean(np.arange(1, 11) / 20))


def test_evd_error_thresholds_and_failures():
    assert len(evd_module.THRESHOLDS) == 10
    assert evd_module.THRESHOLDS[0] == pytest.approx(1.0) and evd_module.THRESHOLDS[-1] == pytest.approx(20.0)
    H_gt = np.array([[1.0, 0, 5], [0, 1, 3], [0, 0, 1]])
    shifted = H_gt @ np.array([[1.0, 0, 2], [0, 1, 0], [0, 0, 1]])  # 2 px off everywhere
    assert evd_module.visible_part_error((40, 60), (40, 60), H_gt, shifted) == pytest.approx(2.0)
    assert evd_module.visible_part_error((40, 60), (40, 60), H_gt, None) == np.inf
    rows = [{"pair": "a", "n_matches": 10, "h_found": 1, "h_error": 2.0},
            {"pair": "b", "n_matches": 0, "h_found": 0, "h_error": np.inf}]
    summary = evd_module.summarize_evd(rows)
    assert summary["n_failures"] == 1 and summary["acc@1"] == 0.0 and summary["acc@20"] == 0.5
    # 2 px lies between the third threshold (1.95 px) and the fourth (2.71 px)
    assert summary["maa"] == pytest.approx(np.mean([0.0] * 3 + [0.5] * 7))


def test_summaries_by_index_equal_the_summaries():
    rng = np.random.default_rng(0)
    bench = get_benchmark("wxbs")
    rows = []
    for i in range(9):
        curve = np.sort(rng.uniform(0, 1, 20))
        rows.append({"pair": f"c{i % 3}/p{i}", "category": f"c{i % 3}", "n_matches": int(rng.integers(0, 99)),
                     "n_gt": 20, "f_found": int(i != 4), "maa@10": wxbs_module.maa(curve),
                     **{wxbs_module.recall_key(t): float(v) for t, v in zip(wxbs_module.THRESHOLDS, curve)}})
    ev = EvalSettings()
    fast = bench.indexed_summary(rows, ev)
    for idx in ([0, 1, 2, 3, 4, 5, 6, 7, 8], [4, 4, 1, 7], [2, 5, 8, 8, 0]):
        assert fast(idx) == bench.summarize([rows[i] for i in idx], ev)
    summary = bench.summarize(rows, ev)
    assert summary["n_pairs_c1"] == 3 and summary["n_failures"] == 1
    assert summary["maa@10"] == pytest.approx(np.mean([r["maa@10"] for r in rows]))
    evd_bench = get_benchmark("evd")
    evd_rows = [{"pair": str(i), "n_matches": i, "h_found": 1, "h_error": float(e)}
                for i, e in enumerate([0.5, 3.0, np.inf, 12.0, 1.2])]
    fast = evd_bench.indexed_summary(evd_rows, ev)
    for idx in ([0, 1, 2, 3, 4], [2, 2, 3]):
        assert fast(idx) == evd_bench.summarize([evd_rows[i] for i in idx], ev)


def test_wxbs_protocol_preset():
    wxbs_fields = get_protocol("wxbs", "wxbs").eval_fields("wxbs")
    assert wxbs_fields["opencv_method"] == "magsac" and wxbs_fields["fundamental_ransac_px"] == 0.25
    assert wxbs_fields["fundamental_confidence"] == 0.999 and wxbs_fields["fundamental_max_iters"] == 100000
    ev = get_benchmark("evd").resolve_eval("wxbs", ransac_px=2.0)  # --ransac-px still applies on top
    assert ev.opencv_method == "magsac" and ev.homography_ransac_px == 2.0
    assert get_benchmark("wxbs").resolve_eval("default").opencv_method == "ransac"
    with pytest.raises(ValueError, match="opencv_method"):
        EvalSettings(opencv_method="lmeds")


def test_benchmark_scores_a_pair_through_its_estimator(wxbs_root):
    """evaluate_pair on matches that are the ground truth itself: F fits them, so most of them
    are recalled at 1 px; with too few matches F fails and the pair scores 0, counted."""
    bench = get_benchmark("wxbs")
    pair = next(p for p in bench.load_dataset(wxbs_root) if p.name == "WGABS/kremlin")
    corrs = pair.corrs
    ev = bench.resolve_eval("wxbs")
    row = bench.evaluate_pair(pair, Matches(corrs[:, :2], corrs[:, 2:], None), ev)
    assert row["f_found"] == 1 and row["recall@1"] > 0.5 and row["recall@19"] >= row["recall@1"]
    few = bench.evaluate_pair(pair, Matches(corrs[:5, :2], corrs[:5, 2:], None), ev)
    assert few["f_found"] == 0 and few["maa@10"] == 0 and few["recall@19"] == 0


# ----------------------------------------------------------------------------- parity


@pytest.fixture(scope="module")
def reference():
    pytest.importorskip("kornia", reason="wxbs-benchmark's F metric needs kornia")
    return pytest.importorskip("wxbs_benchmark.evaluation",
                               reason="the reference evaluator is absent: pip install wxbs-benchmark==0.0.4")


def _estimated_F(corrs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """F from our estimator on the ground truth moved by 1.5 px of noise, half of it: an F
    whose recall climbs over the thresholds instead of jumping from 0 to 1."""
    pick = rng.permutation(len(corrs))[: max(8, len(corrs) // 2)]
    noisy = corrs[pick] + rng.normal(0, 1.5, (len(pick), 4))
    F = fundamental(noisy[:, :2], noisy[:, 2:], 1.0, 10000, 0.999, "opencv", 0, "magsac")
    assert F is not None
    return F


@pytest.mark.parametrize("subset", ["test", "val"])
def test_wxbs_parity_with_the_reference(reference, wxbs_root, tmp_path, monkeypatch, subset):
    """The same F (ours, on noisy ground truth) into the reference's evaluate_Fs and into ours,
    on every shared pair of the split: the per-pair curves agree to float32 precision."""
    pairs = get_benchmark("wxbs").load_dataset(wxbs_root, split=subset)
    rng = np.random.default_rng(1)
    Fs = [_estimated_F(p.corrs, rng) for p in pairs]
    # The reference reads ./.WxBS/v1.1 from the working folder: a link, never a copy.
    (tmp_path / ".WxBS").symlink_to(wxbs_root, target_is_directory=True)
    monkeypatch.chdir(tmp_path)
    theirs, thresholds = reference.evaluate_Fs(Fs, subset)
    assert list(thresholds) == list(wxbs_module.THRESHOLDS)
    assert [k for k in theirs if k != "average"] == [p.name for p in pairs]  # same pairs, same order
    ours = [wxbs_module.recall_curve(F, p.corrs) for F, p in zip(Fs, pairs)]
    worst = max(float(np.max(np.abs(np.asarray(theirs[p.name], np.float64) - c))) for p, c in zip(pairs, ours))
    assert worst <= 1e-6, worst  # float32 fractions against float64 ones
    average = np.mean(ours, axis=0)
    assert np.max(np.abs(np.asarray(theirs["average"], np.float64) - average)) <= 1e-6
    # the test curves are not trivial: they climb over the thresholds
    assert 0 < average[1] < average[10] < 1


def _estimated_H(pair, rng: np.random.Generator, noise_px: float) -> np.ndarray:
    """H from our estimator on points of image 1 mapped by the ground truth and moved by
    noise_px of noise: errors from a fraction of a pixel (1) through a few (8) to misses (30)."""
    from PIL import Image

    w0, h0 = Image.open(pair.image0).size
    x0 = rng.uniform([0, 0], [w0 - 1, h0 - 1], (200, 2))
    x1 = warp_points(pair.H, x0) + rng.normal(0, noise_px, (200, 2))
    H = homography(x0, x1, 2.0, 10000, 0.999, "opencv", 0, "magsac")
    assert H is not None
    return H


def test_evd_parity_with_the_reference(reference, evd_root, tmp_path, monkeypatch):
    """The same H into the reference's evaluate_Hs and into ours, on all 15 pairs: the errors
    agree to float32 precision (the reference maps points in float32) and the accuracies exactly."""
    from PIL import Image

    pairs = get_benchmark("evd").load_dataset(evd_root)
    rng = np.random.default_rng(2)
    Hs = [_estimated_H(p, rng, (1.0, 8.0, 30.0)[i % 3]) for i, p in enumerate(pairs)]
    # The reference reads ./.EVD/EVD from the working folder (the zip unpacks EVD/): a link.
    (tmp_path / ".EVD").mkdir()
    (tmp_path / ".EVD" / "EVD").symlink_to(evd_root, target_is_directory=True)
    monkeypatch.chdir(tmp_path)
    theirs, thresholds = reference.evaluate_Hs(Hs)
    assert np.allclose(thresholds, evd_module.THRESHOLDS, rtol=0, atol=1e-12)
    shapes = [tuple((h, w) for w, h in (Image.open(p.image0).size, Image.open(p.image1).size)) for p in pairs]
    ours = [evd_module.visible_part_error(s0, s1, p.H, H) for (s0, s1), p, H in zip(shapes, pairs, Hs)]
    theirs_errors = np.array([float(theirs[p.name]) for p in pairs])
    # The reference rounds both H to float32 before mapping: that rounding, not the metric,
    # is the whole difference. Given the rounded matrices, ours agrees to float32 precision...
    f32 = [np.float64(np.float32(m)) for m in (Hs, [p.H for p in pairs])]
    rounded = [evd_module.visible_part_error(s0, s1, Hg, H) for (s0, s1), H, Hg in zip(shapes, *f32)]
    assert np.max(np.abs(theirs_errors - rounded) / theirs_errors) <= 1e-5
    # ...and on the matrices as estimated, to what the rounding moves a point at EVD's
    # coordinates (up to 1536 px): 1e-3 px, 1e-4 of the error where the error is large (a
    # wrong H maps points far out), far below the thresholds' spacing either way.
    assert np.allclose(theirs_errors, ours, rtol=1e-4, atol=2e-3), np.abs(theirs_errors - ours)
    # the accuracies: the same counts of pairs (the reference's are float32 fractions)
    assert np.array_equal(np.rint(np.asarray(theirs["average"], np.float64) * len(pairs)),
                          np.rint(np.asarray(evd_module.accuracy_curve(ours)) * len(pairs)))
    # the errors span the thresholds: some below 1 px, some inside 1..20 px, some beyond
    assert min(ours) < 1 and any(1 < e < 20 for e in ours) and max(ours) > 20, ours


# ----------------------------------------------------------------------------- data sources


def test_sources_unpack_the_release_zips_into_the_layouts_the_loaders_read(tmp_path):
    """Zips laid out as the releases are (WxBS_v1.1.zip: the category folders and a README at
    the top; EVD.zip: one EVD/ folder), unpacked as `download` does, give folders the loaders
    and `download --check` accept: WxBS/v1.1/<category>/<pair>/ and EVD/{1,2,h}/."""
    import zipfile

    from e3cm_bench.data import download
    from e3cm_bench.datasets.sources import get_source

    wxbs, evd = get_source("wxbs"), get_source("evd")
    assert (wxbs.folder, evd.folder) == ("WxBS/v1.1", "EVD")
    assert wxbs.parts[0].file == "WxBS_v1.1.zip" and wxbs.parts[0].md5 == "66da037e7d20487e86db147307615870"
    assert evd.parts[0].file == "EVD.zip" and evd.parts[0].md5 == "7ce52151abdafa71a609424d09e43075"
    assert (wxbs.expected, evd.expected) == ({"pairs": 32}, {"pairs": 15})

    with zipfile.ZipFile(tmp_path / "WxBS_v1.1.zip", "w") as zf:
        zf.writestr("README.txt", "WxBS v1.1")
        for pair in ("WGABS/kremlin", "WGABS/petrzin", "WGSBS/kettle"):
            zf.writestr(f"{pair}/01.png", _PNG)
            zf.writestr(f"{pair}/02.png", _PNG)
            zf.writestr(f"{pair}/corrs.txt", "0.5 0.5 0.5 0.5\n")  # on the 1 x 1 px images
            zf.writestr(f"{pair}/crossval_errors.txt", "0.5\n")
    with zipfile.ZipFile(tmp_path / "EVD.zip", "w") as zf:
        for name in ("adam", "fox"):
            zf.writestr(f"EVD/1/{name}.png", _PNG)
            zf.writestr(f"EVD/2/{name}.png", _PNG)
            zf.writestr(f"EVD/h/{name}.txt", "1 0 0\n0 1 0\n0 0 1\n")
    data = tmp_path / "data"
    download.extract(tmp_path / "WxBS_v1.1.zip", data / wxbs.folder)
    download.extract(tmp_path / "EVD.zip", data / evd.folder)
    assert (data / "WxBS" / "v1.1" / "WGSBS" / "kettle" / "corrs.txt").is_file()
    assert (data / "EVD" / "h" / "fox.txt").is_file()
    pairs = get_benchmark("wxbs").load_dataset(data / wxbs.folder)
    assert [p.name for p in pairs] == ["WGABS/kremlin", "WGSBS/kettle"]  # petrzin: validation
    assert len(get_benchmark("evd").load_dataset(data / evd.folder)) == 2
    # a copy short of the release's counts is named incomplete, with the counts
    with pytest.raises(download.DownloadError, match="pairs 2 of 32"):
        download.check(wxbs, data)
    with pytest.raises(download.DownloadError, match="pairs 2 of 15"):
        download.check(evd, data)


@pytest.mark.parametrize("estimator, method", [("opencv", "ransac"), ("opencv", "magsac"), ("poselib", "ransac")])
def test_fundamental_estimators_fit_a_known_scene_despite_outliers(estimator, method):
    if estimator == "poselib":
        pytest.importorskip("poselib", reason="PoseLib is not installed")
    rng = np.random.default_rng(3)
    X = rng.uniform([-2, -2, 4], [2, 2, 8], (150, 3))
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    R = np.array([[np.cos(0.2), 0, np.sin(0.2)], [0, 1, 0], [-np.sin(0.2), 0, np.cos(0.2)]])
    x0 = (X @ K.T)[:, :2] / X[:, 2:]
    Y = X @ R.T + [1.0, 0.1, 0.0]
    x1 = (Y @ K.T)[:, :2] / Y[:, 2:]
    x1[:30] = rng.uniform(0, 640, (30, 2))  # 20 % outliers
    F = fundamental(x0, x1, 1.0, 10000, 0.999, estimator, 0, method)
    assert F is not None
    d = wxbs_module.symmetric_epipolar_distance(F, x0[30:], x1[30:])
    assert np.median(d) < 0.1, np.median(d)
    assert fundamental(x0[:6], x1[:6], 1.0, 100, 0.999, estimator, 0, method) is None  # too few points
    # the same seed gives the same F: an evaluation is repeatable
    assert np.array_equal(F, fundamental(x0, x1, 1.0, 10000, 0.999, estimator, 0, method))
    with pytest.raises(ValueError, match="unknown OpenCV method"):
        fundamental(x0, x1, 1.0, 100, 0.999, estimator, 0, "lmeds")


def test_drawings_call_matches_right_by_the_ground_truth(wxbs_root, evd_root):
    """--viz colours: WxBS through the F of the hand-labelled correspondences themselves, EVD
    through its H; the ground truth is right, the same points shifted 40 px are not."""
    ev = EvalSettings()
    bench = get_benchmark("wxbs")
    pair = next(p for p in bench.load_dataset(wxbs_root) if p.name == "WGABS/kremlin")
    corrs = pair.corrs
    right = bench.correct_mask(pair, Matches(corrs[:, :2], corrs[:, 2:], None), ev)
    wrong = bench.correct_mask(pair, Matches(corrs[:, :2], corrs[:, 2:] + [0.0, 40.0], None), ev)
    assert right.mean() > 0.8 and wrong.mean() < 0.2
    bench = get_benchmark("evd")
    pair = bench.load_dataset(evd_root)[0]
    x0 = np.array([[100.0, 100.0], [200.0, 150.0], [300.0, 250.0]])
    x1 = warp_points(pair.H, x0)
    assert bench.correct_mask(pair, Matches(x0, x1, None), ev).all()
    assert not bench.correct_mask(pair, Matches(x0, x1 + 40.0, None), ev).any()


def test_repeats_on_wxbs_where_a_resample_lacks_a_category(wxbs_root):
    """--repeats K on WxBS: a bootstrap resample that draws no pair of a category has no
    per-category keys (n_matches_WGBS, ...); the mean over repeats skips them there, as one
    evaluation's resample does (it raised KeyError before)."""
    from dataclasses import replace

    from e3cm_bench.ground.matches import Matches
    from e3cm_bench.pipeline.evaluate import evaluate_stage

    bench = get_benchmark("wxbs")
    pairs = list(bench.load_dataset(wxbs_root))
    by_name = {p.name: p for p in pairs}

    class Labelled:  # the hand-labelled correspondences as the matches: no matcher needed
        def read(self, name):
            corrs = by_name[name].corrs
            return Matches(corrs[:, :2].astype(np.float32), corrs[:, 2:4].astype(np.float32),
                           np.ones(len(corrs), np.float32), {})

    ev = replace(bench.resolve_eval(), repeats=2)
    _, summary, _ = evaluate_stage(bench, pairs, Labelled(), ev)
    assert summary["repeats"] == 2 and "maa@10_sd" in summary
    assert summary["maa@10_lo"] <= summary["maa@10"] <= summary["maa@10_hi"]
