"""Matches in and out: every format round-trips
a sift run to the same per_pair.csv on a homography and a pose benchmark; a COLMAP database
reads back in pycolmap; hloc's layout read as hloc's io functions read it; bad files refused
in one line; the half-pixel check catches a file in the other convention."""

from __future__ import annotations

import io
import zipfile

import h5py
import numpy as np
import pandas as pd
import pytest
import yaml

from e3cm_bench.storage.cache import MatchCache
from e3cm_bench.interchange import MAX_POINTS, from_origin, to_origin
from e3cm_bench.interchange.gluefactory import hpatches_keys
from helpers import flat, invoke, one_line_error

FORMATS = ("hloc", "npz", "gluefactory", "colmap")


def needs(fmt: str) -> None:
    if fmt == "colmap":
        pytest.importorskip("pycolmap", reason="the colmap extra (pycolmap) is not installed")


def import_args(fmt: str, folder) -> list:
    return {"hloc": ["--hloc", folder / "features.h5", folder / "matches.h5"], "npz": ["--npz", folder],
            "gluefactory": ["--gluefactory", folder / "predictions.h5"], "colmap": ["--colmap", folder / "database.db"]}[fmt]


@pytest.fixture(scope="module")
def hpatches_run(shared_data, tmp_path_factory):
    root = shared_data / "hpatches-sequences-release"
    out = tmp_path_factory.mktemp("hp") / "sift"
    select = ["--root", root, "--sequences", "v_boat", "--limit", "3"]
    assert invoke("hpatches", *select, "--out", out, "--matcher", "sift").exit_code == 0
    return out, ["hpatches", *select]


@pytest.fixture(scope="module")
def kitti_run(shared_data, tmp_path_factory):
    root = shared_data / "megadepth_test_1500"
    out = tmp_path_factory.mktemp("kitti") / "sift"
    select = ["--root", root, "--scene-info", root / "scene_info" / "kitti00_seq.npz", "--limit", "3"]
    assert invoke("megadepth", *select, "--out", out, "--matcher", "sift").exit_code == 0
    return out, ["megadepth", *select]


def round_trip(run, fmt: str, tmp_path, *extra):
    out, select = run
    exported = tmp_path / f"to-{fmt}"
    assert invoke("export", out, exported, "--to", fmt).exit_code == 0
    back = tmp_path / f"from-{fmt}"
    result = invoke("import", *select, "--out", back, *import_args(fmt, exported), *extra)
    assert result.exit_code == 0
    return exported, back, result


@pytest.mark.parametrize("fmt", FORMATS)
def test_a_pose_run_round_trips_to_the_same_per_pair_csv(kitti_run, fmt, tmp_path):
    needs(fmt)
    _, back, _ = round_trip(kitti_run, fmt, tmp_path)
    assert (back / "per_pair.csv").read_bytes() == (kitti_run[0] / "per_pair.csv").read_bytes()
    config = yaml.safe_load((back / "config.yaml").read_text())
    assert config["identity"]["imported"]["format"] == fmt and config["dataset"]["limit"] == 3


@pytest.mark.parametrize("fmt", ("hloc", "npz", "gluefactory"))
def test_a_homography_run_round_trips_to_the_same_per_pair_csv(hpatches_run, fmt, tmp_path):
    _, back, result = round_trip(hpatches_run, fmt, tmp_path)
    assert (back / "per_pair.csv").read_bytes() == (hpatches_run[0] / "per_pair.csv").read_bytes()
    assert "warning: pixel convention" not in result.output
    check = yaml.safe_load((back / "config.yaml").read_text())["pixel_origin_check"]
    assert check["other_fits_better"] is False and check["z"] < 0  # half a pixel off fits worse


def test_a_homography_run_through_colmap_loses_at_most_one_float32_step(hpatches_run, tmp_path):
    """COLMAP stores keypoints as float32 in its corner convention: x + 0.5 is not a float32 for
    half of the x in [2^k - 0.5, 2^k), so those come back one step off. The matches, their
    counts and MMA are the same; the homography error moves by less than 1e-5 px."""
    pytest.importorskip("pycolmap", reason="the colmap extra (pycolmap) is not installed")
    _, back, _ = round_trip(hpatches_run, "colmap", tmp_path)
    native, imported = MatchCache(hpatches_run[0] / "matches.h5"), MatchCache(back / "matches.h5")
    moved = total = 0
    for name in native.names():
        a, b = native.read(name), imported.read(name)
        for x, y in ((a.keypoints0, b.keypoints0), (a.keypoints1, b.keypoints1)):
            steps = np.abs(x.view(np.int32).astype(np.int64) - y.view(np.int32).astype(np.int64))
            assert steps.max() <= 1
            moved, total = moved + int(np.count_nonzero(steps)), total + steps.size
    assert 0 < moved < 0.01 * total
    a, b = (pd.read_csv(d / "per_pair.csv") for d in (hpatches_run[0], back))
    pd.testing.assert_frame_equal(a.drop(columns="h_error"), b.drop(columns="h_error"))
    np.testing.assert_allclose(a["h_error"], b["h_error"], rtol=0, atol=1e-5)  # pixels


def hloc_pair_key(name0: str, name1: str, separator: str = "/") -> str:
    """hloc's names_to_pair (separator "/") and names_to_pair_old ("_"), as its parsers.py defines them."""
    return separator.join(n.replace("/", "-") for n in (name0, name1))


def hloc_get_matches(path, name0: str, name1: str):
    """(matches (M, 2), scores (M,)) as hloc/utils/io.py's get_matches returns them at c13273b:
    find_pair tries the pair key, the swapped key, then both older '_' keys; idx =
    where(matches0 != -1); the columns flipped for a pair stored the other way round."""
    with h5py.File(path, "r") as f:
        for key, reverse in ((hloc_pair_key(name0, name1), False), (hloc_pair_key(name1, name0), True),
                             (hloc_pair_key(name0, name1, "_"), False), (hloc_pair_key(name1, name0, "_"), True)):
            if key in f:
                break
        else:
            raise AssertionError(f"hloc's find_pair would not find {name0}, {name1}")
        matches0, scores0 = f[key]["matches0"].__array__(), f[key]["matching_scores0"].__array__()
    idx = np.where(matches0 != -1)[0]
    matches = np.stack([idx, matches0[idx]], -1)
    return (np.flip(matches, -1) if reverse else matches), scores0[idx]


def hloc_get_keypoints(path, name: str) -> np.ndarray:
    """hloc's get_keypoints: f[name]["keypoints"] read whole."""
    with h5py.File(path, "r") as f:
        return f[name]["keypoints"].__array__()


def rows(*columns) -> list:
    """A pair's matches as a sorted list of rows (hloc returns them in keypoint order)."""
    return sorted(map(tuple, np.concatenate([np.asarray(c, np.float64).reshape(len(c), -1) for c in columns], axis=1).tolist()))


@pytest.mark.parametrize("which", ["hpatches", "kitti"])
def test_the_hloc_export_reads_as_hlocs_io_functions_read_it(which, request, tmp_path):
    """hloc is not on PyPI (its README installs it from a git checkout, which needs the network),
    so the files are read as hloc/utils/io.py's get_keypoints and get_matches read them
    (helpers above, written from that code's behaviour): every pair's matches and scores come
    back, in either image order, from one keypoint list per image that repeats no location
    (an appended keypoint only where a pair matched one keypoint twice); e3cm_order gives the
    run's order; pairs.txt lists the pairs as hloc's pairs parser splits them."""
    out, _ = request.getfixturevalue(f"{which}_run")
    exported = tmp_path / "hloc"
    result = invoke("export", out, exported, "--to", "hloc")
    assert result.exit_code == 0 and "one keypoint list per image" in result.output
    cache = MatchCache(out / "matches.h5")
    features, matches_path = exported / "features.h5", exported / "matches.h5"
    names = [line.split() for line in (exported / "pairs.txt").read_text().splitlines()]
    assert len(names) == len(cache.names()) and all(len(n) == 2 for n in names)
    appended: dict[str, int] = {}
    with h5py.File(features, "r") as f:
        for name0, _ in names:
            assert f[name0]["keypoints"].dtype == np.float32
    for (name0, name1), pair in zip(names, cache.names()):
        native = cache.read(pair)
        k0, k1 = hloc_get_keypoints(features, name0), hloc_get_keypoints(features, name1)
        for a, b, flip in ((name0, name1, False), (name1, name0, True)):
            matches, scores = hloc_get_matches(matches_path, a, b)
            if flip:
                matches = np.flip(matches, -1)
            assert rows(k0[matches[:, 0]], k1[matches[:, 1]], scores) == rows(native.keypoints0, native.keypoints1,
                                                                                native.scores)
        with h5py.File(matches_path, "r") as f:
            group = f[hloc_pair_key(name0, name1)]
            order = group["e3cm_order"][()]
            m0 = group["matches0"][()]
            assert m0.dtype == np.int16 and len(m0) == len(k0)
            np.testing.assert_array_equal(k0[order], native.keypoints0)
            np.testing.assert_array_equal(k1[m0[order]], native.keypoints1)
            np.testing.assert_array_equal(group["matching_scores0"][()][order], native.scores)
        repeats = len(native.keypoints0) - len(np.unique(native.keypoints0, axis=0))
        appended[name0] = appended.get(name0, 0) + repeats  # a keypoint the pair matched twice: its own entry
    for name in {n for pair in names for n in pair}:  # each location once, but for those entries
        points = hloc_get_keypoints(features, name)
        assert len(points) - len(np.unique(points, axis=0)) == appended.get(name, 0)
    assert sum(appended.values()) > 0  # SIFT lists a location once per orientation: the case arises
    total = sum(len(hloc_get_keypoints(features, n)) for n in {n for pair in names for n in pair})
    assert total < sum(2 * len(cache.read(p)) for p in cache.names())  # merged: fewer than one per match side


def test_gluefactory_names_hpatches_pairs_by_its_own_index(hpatches_run, shared_data, tmp_path):
    out, _ = hpatches_run
    exported = tmp_path / "gf"
    assert invoke("export", out, exported, "--to", "gluefactory").exit_code == 0
    root = shared_data / "hpatches-sequences-release"
    rank = sorted(p.name for p in root.iterdir()).index("v_boat")  # no large sequence sorts before v_boat here
    with h5py.File(exported / "predictions.h5", "r") as f:
        assert sorted(f["v_boat"]) == sorted(f"{5 * rank + k}.ppm" for k in range(3))
        group = f[f"v_boat/{5 * rank}.ppm"]
        native = MatchCache(out / "matches.h5").read("v_boat/1-2")
        assert group["keypoints0"].dtype == np.float64
        np.testing.assert_array_equal(group["keypoints0"][()] - 0.5, native.keypoints0)  # corner convention
        np.testing.assert_array_equal(group["matches0"][()], np.arange(len(native)))
    assert hpatches_keys(root, ignore_large=True)[("v_boat", 2)] == f"v_boat/{5 * rank}.ppm"


def test_a_kitti_colmap_database_reads_back_in_pycolmap(kitti_run, tmp_path):
    """Match counts as in per_pair.csv; the stored two-view geometries hold the evaluation's
    inliers; pycolmap's own estimate at 0.5 px finds inlier counts close to ours (docs/interchange.md)."""
    pycolmap = pytest.importorskip("pycolmap", reason="the colmap extra (pycolmap) is not installed")
    out, _ = kitti_run
    exported = tmp_path / "colmap"
    assert invoke("export", out, exported, "--to", "colmap").exit_code == 0
    per_pair = pd.read_csv(out / "per_pair.csv").set_index("pair")
    db = pycolmap.Database.open(str(exported / "database.db"))
    try:
        images = {image.name: image for image in db.read_all_images()}
        cameras = {camera.camera_id: camera for camera in db.read_all_cameras()}
        assert len(images) == 6 and all(c.model == pycolmap.CameraModelId.PINHOLE for c in cameras.values())
        for name, row in per_pair.iterrows():
            frames = name.split("/")[1].split("--")
            a, b = (images[f"Undistorted_SfM/kitti00/images/{frame}.png"] for frame in frames)
            matches = db.read_matches(a.image_id, b.image_id)
            assert len(matches) == row["n_matches"] + row["n_duplicates"]  # every match the run holds
            ours = db.read_two_view_geometry(a.image_id, b.image_id)
            assert ours.config == pycolmap.TwoViewGeometryConfiguration.CALIBRATED
            assert 0.5 * len(matches) < len(ours.inlier_matches) < len(matches)
            options = pycolmap.TwoViewGeometryOptions()
            options.ransac.max_error, options.ransac.random_seed = 0.5, 0
            theirs = pycolmap.estimate_two_view_geometry(
                cameras[a.camera_id], db.read_keypoints(a.image_id).astype(np.float64),
                cameras[b.camera_id], db.read_keypoints(b.image_id).astype(np.float64), matches, options)
            print(name, len(matches), len(ours.inlier_matches), len(theirs.inlier_matches))
            assert theirs.config == pycolmap.TwoViewGeometryConfiguration.CALIBRATED
            assert abs(len(theirs.inlier_matches) - len(ours.inlier_matches)) < 0.15 * len(ours.inlier_matches)
    finally:
        db.close()


def test_a_colmap_database_with_a_missing_image_or_bad_keypoints_is_refused_in_one_line(kitti_run, tmp_path):
    pycolmap = pytest.importorskip("pycolmap", reason="the colmap extra (pycolmap) is not installed")
    out, select = kitti_run
    exported = tmp_path / "colmap"
    assert invoke("export", out, exported, "--to", "colmap").exit_code == 0
    database = exported / "database.db"
    original = database.read_bytes()

    def edit(change) -> None:
        database.write_bytes(original)
        db = pycolmap.Database.open(str(database))
        try:
            change(db, {image.name: image for image in db.read_all_images()})
        finally:
            db.close()

    def renamed(db, images):
        image = images["Undistorted_SfM/kitti00/images/000103.png"]
        image.name = "elsewhere/000103.png"
        db.update_image(image)

    edit(renamed)
    line = one_line_error(invoke("import", *select, "--out", tmp_path / "a", "--colmap", database))
    assert "1 of 3 pairs are not in the source (first: kitti00_seq/000100--000103" in line
    assert "an image named Undistorted_SfM/kitti00/images/000103.png, which the database lacks" in line

    def outside(db, images):
        image_id = images["Undistorted_SfM/kitti00/images/000100.png"].image_id
        db.update_keypoints(image_id, db.read_keypoints(image_id) + np.float32([5000, 0]))

    edit(outside)
    line = one_line_error(invoke("import", *select, "--out", tmp_path / "b", "--colmap", database))
    assert line.startswith("error: pair kitti00_seq/000100--000103: keypoints0:") and "outside the" in line

    def too_few(db, images):
        image_id = images["Undistorted_SfM/kitti00/images/000100.png"].image_id
        db.update_keypoints(image_id, db.read_keypoints(image_id)[:10])

    edit(too_few)
    line = one_line_error(invoke("import", *select, "--out", tmp_path / "c", "--colmap", database))
    assert "points to keypoint" in line and "which has 10" in line


def test_a_file_in_the_other_convention_is_detected_on_hpatches(hpatches_run, tmp_path):
    """The hloc export (centre convention) imported as if written in the corner convention is
    half a pixel off in both images: the check warns and names the fix; mma@1 shows it."""
    out, select = hpatches_run
    exported = tmp_path / "hloc"
    assert invoke("export", out, exported, "--to", "hloc").exit_code == 0
    back = tmp_path / "shifted"
    result = invoke("import", *select, "--out", back, *import_args("hloc", exported), "--pixel-origin", "corner")
    assert result.exit_code == 0
    assert "the file looks written in the other pixel convention" in result.output
    assert "--pixel-origin center" in " ".join(result.output.split())
    check = yaml.safe_load((back / "config.yaml").read_text())["pixel_origin_check"]
    assert check["other_fits_better"] is True and check["shift_px"] == 0.5 and check["mma@1_shifted"] > check["mma@1"]
    identity = yaml.safe_load((back / "config.yaml").read_text())["identity"]["imported"]
    assert identity["pixel_origin"] == "corner"  # another origin is another source
    native = pd.read_csv(out / "per_pair.csv")
    assert (pd.read_csv(back / "per_pair.csv")["mma@1"] < native["mma@1"]).all()


def test_pixel_conversions_are_each_others_inverse_exactly():
    points = np.float32([[0, 0], [1.9999999, 511.99997], [-0.5, 1023.75]])
    assert np.array_equal(to_origin(points, "corner") - 0.5, points.astype(np.float64))
    assert np.array_equal(from_origin(to_origin(points, "corner"), "corner").astype(np.float32), points)
    assert np.array_equal(to_origin(points, "center"), points)
    with pytest.raises(ValueError, match="--pixel-origin must be one of center, corner"):
        to_origin(points, "middle")


def test_export_refuses_to_overwrite_and_names_a_missing_extra_cleanly(hpatches_run, tmp_path):
    out, _ = hpatches_run
    assert invoke("export", out, tmp_path / "x", "--to", "hloc").exit_code == 0
    line = one_line_error(invoke("export", out, tmp_path / "x", "--to", "hloc"))
    assert "features.h5: already exists; pass --overwrite" in line
    assert invoke("export", out, tmp_path / "x", "--to", "hloc", "--overwrite").exit_code == 0
    line = one_line_error(invoke("export", out, tmp_path / "y", "--to", "bundler"))
    assert "--to must be one of colmap, gluefactory, hloc, npz" in line


def test_export_never_writes_into_a_run_folder(hpatches_run, kitti_run, tmp_path):
    """OUT = the run, a folder inside it, or another run folder: one line, and the run's own
    files stay as they were (an --overwrite hloc export used to replace its matches.h5). An OUT
    that holds the run is allowed: nothing export writes lands in the run."""
    import shutil

    holder = tmp_path / "runs"
    run = holder / "sift"
    shutil.copytree(hpatches_run[0], run)
    before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file() and p.name != ".lock"}
    for out, fmt, said in ((run, "hloc", "is the run folder"), (run / "exported", "colmap", "is inside the run folder"),
                           (kitti_run[0], "npz", "is the run folder"), (run / "shards" / "x", "gluefactory", "is inside")):
        if fmt == "colmap":
            pytest.importorskip("pycolmap", reason="the colmap extra (pycolmap) is not installed")
        line = one_line_error(invoke("export", run, out, "--to", fmt, "--overwrite"))
        assert said in line and "never into one" in line
    assert not (run / "exported").exists() and not (run / "shards").exists()
    assert invoke("export", run, holder, "--to", "hloc").exit_code == 0  # beside the run
    assert {p.name: p.read_bytes() for p in run.iterdir() if p.is_file() and p.name != ".lock"} == before
    assert (holder / "matches.h5").is_file()


def test_merge_px_is_recorded_and_refused_where_it_means_nothing(kitti_run, tmp_path):
    out, _ = kitti_run
    exact, near = (invoke("export", out, tmp_path / name, "--to", "hloc", *extra)
                   for name, extra in (("exact", ()), ("near", ("--merge-px", "2"))))
    assert exact.exit_code == near.exit_code == 0
    assert "(exact repeats merged)" in flat(exact.output) and "points within 2 px merged" in flat(near.output)
    from e3cm_bench.pipeline.export import export_run

    found = export_run(out, "hloc", tmp_path / "again", merge_px=2.0)
    assert found["merge_px"] == 2.0 and found["n_keypoints_merged"] > 0 and found["mean_track_length"] >= 2
    assert "--merge-px applies to --to colmap and hloc" in one_line_error(
        invoke("export", out, tmp_path / "npz", "--to", "npz", "--merge-px", "1"))
    assert "--merge-px must be a radius of 0 or more pixels" in one_line_error(
        invoke("export", out, tmp_path / "neg", "--to", "hloc", "--merge-px", "-1"))


# --------------------------------------------------------------------------- bad hloc and npz files


@pytest.fixture()
def hloc_files(hpatches_run, tmp_path):
    out, select = hpatches_run
    exported = tmp_path / "hloc"
    assert invoke("export", out, exported, "--to", "hloc").exit_code == 0
    return exported, select


def break_pair(exported, **datasets) -> None:
    """Replace datasets of the first pair's group (v_boat/1.ppm, v_boat/2.ppm) in matches.h5."""
    with h5py.File(exported / "matches.h5", "a") as f:
        group = f["v_boat-1.ppm/v_boat-2.ppm"]
        for name, data in datasets.items():
            del group[name]
            group.create_dataset(name, data=data) if not callable(data) else data(group, name)


@pytest.mark.parametrize("case, expected", [
    ("float", "matches0: expected integer indices, got floats"),
    ("bytes", "matches0: expected integer indices, got bytes"),
    ("minus5", "= -5: not -1 (no match) nor an index into the"),
])
def test_bad_hloc_matches_are_refused_in_one_line(hloc_files, case, expected, tmp_path):
    exported, select = hloc_files
    with h5py.File(exported / "matches.h5", "r") as f:
        matches0 = f["v_boat-1.ppm/v_boat-2.ppm/matches0"][()]
    bad = {"float": matches0.astype(np.float64), "bytes": np.array([b"1"] * len(matches0)),
           "minus5": np.where(np.arange(len(matches0)) == 3, -5, matches0)}[case]
    break_pair(exported, matches0=bad)
    line = one_line_error(invoke("import", *select, "--out", tmp_path / "o", *import_args("hloc", exported)))
    assert line.startswith("error: pair v_boat/1-2: ") and expected in line


def test_0d_complex_and_huge_hloc_keypoints_are_refused_in_one_line(hloc_files, tmp_path):
    exported, select = hloc_files
    features = exported / "features.h5"
    original = features.read_bytes()
    cases = {
        "0d": (lambda g: g.create_dataset("keypoints", data=np.float32(3)), "keypoints has shape (), expected N x 2"),
        "complex": (lambda g: g.create_dataset("keypoints", data=g.file["v_boat/2.ppm/keypoints"][()] * (1 + 1j)),
                    "keypoints: expected real numbers, got complex numbers"),
        # a few KB on disk, 3 GB declared: never read
        "huge": (lambda g: g.create_dataset("keypoints", shape=(400_000_000, 2), dtype=np.float32, chunks=(65536, 2),
                                            compression="gzip"), f"more than the {MAX_POINTS} rows an import reads"),
    }
    for case, (make, expected) in cases.items():
        features.write_bytes(original)
        with h5py.File(features, "a") as f:
            del f["v_boat/1.ppm/keypoints"]
            make(f["v_boat/1.ppm"])
        assert features.stat().st_size < 10 << 20
        line = one_line_error(invoke("import", *select, "--out", tmp_path / case, *import_args("hloc", exported)))
        assert line.startswith("error: pair v_boat/1-2: ") and expected in line, case


def npy_header_only(shape, dtype="<f4") -> bytes:
    """An .npy member declaring `shape` and holding none of its data."""
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(buffer, {"descr": dtype, "fortran_order": False, "shape": shape})
    return buffer.getvalue()


def test_huge_and_complex_npz_keypoints_are_refused_in_one_line(hpatches_run, tmp_path):
    out, select = hpatches_run
    folder = tmp_path / "npz"
    assert invoke("export", out, folder, "--to", "npz").exit_code == 0
    path = folder / "v_boat/1-2.npz"
    with np.load(path) as data:
        k0, k1 = data["keypoints0"], data["keypoints1"]
    with zipfile.ZipFile(path, "w") as archive:  # 3 GB of keypoints declared in a file of a few hundred bytes
        archive.writestr("keypoints0.npy", npy_header_only((375_000_000, 2)))
        archive.writestr("keypoints1.npy", npy_header_only((375_000_000, 2)))
    line = one_line_error(invoke("import", *select, "--out", tmp_path / "a", "--npz", folder))
    assert "v_boat/1-2.npz: keypoints0 declares shape (375000000, 2) (2861 MiB)" in line
    np.savez(path, keypoints0=k0 * (1 + 0j), keypoints1=k1)
    line = one_line_error(invoke("import", *select, "--out", tmp_path / "b", "--npz", folder))
    assert "keypoints0: expected real numbers, got complex numbers" in line
