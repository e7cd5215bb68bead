"""Matches in and out (issue 45, and the import findings of issue 44): every format round-trips
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

from e3cm_bench.cache import MatchCache
from e3cm_bench.interchange import MAX_POINTS, from_origin, to_origin
from e3cm_bench.interchange.gluefactory import hpatches_keys
from helpers import invoke, one_line_error

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


def test_the_hloc_export_reads_as_hlocs_io_functions_read_it(hpatches_run, tmp_path):
    """hloc is not on PyPI (its README installs it from a git checkout, which needs the network),
    so this reads the files as hloc/utils/io.py's get_keypoints and get_matches do, written from
    that layout: keypoints at f[name]["keypoints"], the pair at names_to_pair(name0, name1) with
    matches0 and matching_scores0, idx = where(matches0 != -1)."""
    out, _ = hpatches_run
    exported = tmp_path / "hloc"
    assert invoke("export", out, exported, "--to", "hloc").exit_code == 0
    cache = MatchCache(out / "matches.h5")
    with h5py.File(exported / "features.h5", "r") as features, h5py.File(exported / "matches.h5", "r") as matches:
        for name in cache.names():
            sequence, ids = name.split("/")
            name0, name1 = (f"{sequence}/{i}.ppm" for i in ids.split("-"))
            pair = "/".join(n.replace("/", "-") for n in (name0, name1))
            m0, s0 = matches[pair]["matches0"].__array__(), matches[pair]["matching_scores0"].__array__()
            assert m0.dtype == np.int16 and features[name0]["keypoints"].dtype == np.float32
            idx = np.where(m0 != -1)[0]
            k0 = features[name0]["keypoints"].__array__()[idx]
            k1 = features[name1]["keypoints"].__array__()[m0[idx]]
            native = cache.read(name)
            np.testing.assert_array_equal(k0, native.keypoints0)
            np.testing.assert_array_equal(k1, native.keypoints1)
            np.testing.assert_array_equal(s0[idx], native.scores)
            assert tuple(features[name0]["image_size"][()]) == tuple(native.info["size0"])


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
    assert "--to must be one of colmap, hloc, gluefactory, npz" in line


# --------------------------------------------------------------------------- bad hloc and npz files (issue 44)


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
