"""`import --hloc` / `--gluefactory` read only what the named HDF5 file holds itself: a soft or
external link, a virtual dataset (whose source may be missing: HDF5 then reads its fill value
without a word) or external raw storage is refused in one line naming the file and the
object, before anything is read; the same files without those import and score."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import pytest

from helpers import invoke, one_line_error

PAIRS = ("v_boat/1-2", "v_boat/1-3")


@pytest.fixture(scope="module")
def boat(shared_data) -> tuple[Path, list[str]]:
    root = shared_data / "hpatches-sequences-release"
    return root, ["hpatches", "--root", root, "--sequences", "v_boat", "--limit", len(PAIRS)]


def true_points(root: Path) -> dict[str, np.ndarray]:
    """Image name -> keypoints: a grid on image 1 and its images under the true homographies,
    so that every match is correct (the pair scores MMA 1 where the values are read)."""
    grid = np.stack(np.meshgrid(np.arange(100, 700, 60.0), np.arange(100, 500, 60.0)), -1).reshape(-1, 2)
    points = {"v_boat/1.ppm": grid}
    for k in (2, 3):
        H = np.loadtxt(root / "v_boat" / f"H_1_{k}")
        warped = np.c_[grid, np.ones(len(grid))] @ H.T
        points[f"v_boat/{k}.ppm"] = warped[:, :2] / warped[:, 2:]
    return points


def hloc_files(folder: Path, root: Path, change=None) -> tuple[Path, Path]:
    """hloc's features.h5 and matches.h5 for PAIRS; change(features, matches, folder) edits them."""
    points = true_points(root)
    features, matches = folder / "features.h5", folder / "matches.h5"
    with h5py.File(features, "w") as f, h5py.File(matches, "w") as m:
        for name, k in points.items():
            f.create_group(name).create_dataset("keypoints", data=k.astype(np.float32))
        for pair in PAIRS:
            key = f"v_boat-1.ppm/v_boat-{pair[-1]}.ppm"
            m.create_group(key).create_dataset("matches0", data=np.arange(len(points["v_boat/1.ppm"])))
        if change is not None:
            change(f, m, folder)
    return features, matches


def gluefactory_file(folder: Path, root: Path, change=None) -> Path:
    """glue-factory's predictions.h5 for PAIRS (v_boat is the second sequence of the shared
    root, so its pairs (1, 2) and (1, 3) are named v_boat/5.ppm and v_boat/6.ppm)."""
    points = true_points(root)
    path = folder / "predictions.h5"
    with h5py.File(path, "w") as f:
        for index, k in ((5, 2), (6, 3)):
            group = f.create_group(f"v_boat/{index}.ppm")
            group.create_dataset("keypoints0", data=points["v_boat/1.ppm"] + 0.5)
            group.create_dataset("keypoints1", data=points[f"v_boat/{k}.ppm"] + 0.5)
            group.create_dataset("matches0", data=np.arange(len(points["v_boat/1.ppm"])))
        if change is not None:
            change(f, folder)
    return path


def virtual_from_missing_file(file: h5py.File, where: str, like: np.ndarray, folder: Path) -> None:
    """`where` replaced by a virtual dataset over a file that is then deleted."""
    source = folder / "gone.h5"
    with h5py.File(source, "w") as s:
        s.create_dataset("data", data=like)
    layout = h5py.VirtualLayout(shape=like.shape, dtype=like.dtype)
    layout[:] = h5py.VirtualSource(str(source), "data", shape=like.shape)
    del file[where]
    file.create_virtual_dataset(where, layout, fillvalue=3)
    source.unlink()


def hloc_virtual(f, m, folder):
    virtual_from_missing_file(f, "v_boat/2.ppm/keypoints", f["v_boat/2.ppm/keypoints"][()], folder)


def hloc_loop(f, m, folder):
    del m["v_boat-1.ppm/v_boat-3.ppm"]
    m["v_boat-1.ppm/v_boat-3.ppm"] = h5py.SoftLink("/loop")
    m["loop"] = h5py.SoftLink("/v_boat-1.ppm/v_boat-3.ppm")


def hloc_external(f, m, folder):
    """Pair (1, 3)'s group lives in another file (holding its true matches)."""
    with h5py.File(folder / "other.h5", "w") as other:
        other.create_group("pair").create_dataset("matches0", data=m["v_boat-1.ppm/v_boat-3.ppm/matches0"][()])
    del m["v_boat-1.ppm/v_boat-3.ppm"]
    m["v_boat-1.ppm/v_boat-3.ppm"] = h5py.ExternalLink(str(folder / "other.h5"), "/pair")


def hloc_alias(f, m, folder):
    """Pair (1, 3) named as a soft link to pair (1, 2)'s matches."""
    del m["v_boat-1.ppm/v_boat-3.ppm"]
    m["v_boat-1.ppm/v_boat-3.ppm"] = h5py.SoftLink("/v_boat-1.ppm/v_boat-2.ppm")


def hloc_external_storage(f, m, folder):
    values = f["v_boat/3.ppm/keypoints"][()]
    raw = folder / "raw.bin"
    raw.write_bytes(values.tobytes())
    del f["v_boat/3.ppm/keypoints"]
    f.create_dataset("v_boat/3.ppm/keypoints", shape=values.shape, dtype=values.dtype,
                     external=[(str(raw), 0, values.nbytes)])


HLOC_CASES = {
    "virtual": (hloc_virtual, "features.h5: /v_boat/2.ppm/keypoints is a virtual dataset (its values are read from"),
    "loop": (hloc_loop, "matches.h5: /loop is a soft link to /v_boat-1.ppm/v_boat-3.ppm"),
    "external": (hloc_external, "matches.h5: /v_boat-1.ppm/v_boat-3.ppm is an external link to"),
    "alias": (hloc_alias, "matches.h5: /v_boat-1.ppm/v_boat-3.ppm is a soft link to /v_boat-1.ppm/v_boat-2.ppm"),
    "external-storage": (hloc_external_storage, "features.h5: /v_boat/3.ppm/keypoints stores its values in external"),
}


def test_plain_files_import_and_score(boat, tmp_path):
    """The control: the same files without links import, and every match is correct."""
    root, select = boat
    features, matches = hloc_files(tmp_path, root)
    assert invoke("import", *select, "--out", tmp_path / "hloc", "--hloc", features, matches).exit_code == 0
    assert invoke("import", *select, "--out", tmp_path / "gf", "--gluefactory", gluefactory_file(tmp_path, root)).exit_code == 0
    for run in ("hloc", "gf"):
        rows = pd.read_csv(tmp_path / run / "per_pair.csv")
        assert len(rows) == 2 and (rows["mma@3"] == 1.0).all(), rows


@pytest.mark.parametrize("case", HLOC_CASES)
def test_hloc_files_with_links_or_outside_data_are_refused(boat, tmp_path, case):
    root, select = boat
    change, says = HLOC_CASES[case]
    features, matches = hloc_files(tmp_path, root, change)
    line = one_line_error(invoke("import", *select, "--out", tmp_path / "run", "--hloc", features, matches))
    assert says in line and "an imported file must hold its data itself" in line
    assert not (tmp_path / "run" / "per_pair.csv").exists()


def gf_virtual(f, folder):
    virtual_from_missing_file(f, "v_boat/5.ppm/keypoints1", f["v_boat/5.ppm/keypoints1"][()], folder)


def gf_loop(f, folder):
    del f["v_boat/6.ppm"]
    f["v_boat/6.ppm"] = h5py.SoftLink("/loop")
    f["loop"] = h5py.SoftLink("/v_boat/6.ppm")


def gf_external(f, folder):
    with h5py.File(folder / "other.h5", "w") as other:
        f.copy(f["v_boat/6.ppm"], other, "pair")
    del f["v_boat/6.ppm"]
    f["v_boat/6.ppm"] = h5py.ExternalLink(str(folder / "other.h5"), "/pair")


GF_CASES = {
    "virtual": (gf_virtual, "predictions.h5: /v_boat/5.ppm/keypoints1 is a virtual dataset"),
    "loop": (gf_loop, "predictions.h5: /loop is a soft link to /v_boat/6.ppm"),
    "external": (gf_external, "predictions.h5: /v_boat/6.ppm is an external link to"),
}


@pytest.mark.parametrize("case", GF_CASES)
def test_gluefactory_files_with_links_or_outside_data_are_refused(boat, tmp_path, case):
    root, select = boat
    change, says = GF_CASES[case]
    predictions = gluefactory_file(tmp_path, root, change)
    line = one_line_error(invoke("import", *select, "--out", tmp_path / "run", "--gluefactory", predictions))
    assert says in line and "an imported file must hold its data itself" in line
