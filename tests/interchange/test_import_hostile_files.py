"""Robustness round seven (issue 70): hostile files given to `import`. A COLMAP database with
another schema, a text file, NaN keypoints, matches of unknown image ids, a deleted image, NaN
geometries; hloc and glue-factory HDF5 files with wrong shapes and dtypes, indices out of range
and datasets declaring 2e9 rows. Each is one line naming the file and the problem and a non-zero
exit, before anything is scored, or (NaN geometries: the import reads matches, not geometries)
scores as the clean file does."""

from __future__ import annotations

import sqlite3

import numpy as np
import pandas as pd
import pytest

from helpers import invoke, one_line_error
from interchange.test_import_colmap_sizes import database
from interchange.test_import_hdf5_links import PAIRS, gluefactory_file, hloc_files

pytest.importorskip("pycolmap", reason="the COLMAP format needs pycolmap (the colmap extra)")


@pytest.fixture(scope="module")
def root(shared_data):
    return shared_data / "hpatches-sequences-release"


def _sql(query, args=()):
    def change(path):
        connection = sqlite3.connect(path)
        with connection:
            connection.execute(query, args)
        connection.close()
    return change


def _other_schema(path):
    path.unlink()
    connection = sqlite3.connect(path)
    with connection:
        connection.execute("CREATE TABLE foo (x INTEGER)")
    connection.close()


COLMAP_CASES = {
    "another schema": (_other_schema, "an image named v_boat/1.ppm, which the database lacks"),
    "a text file": (lambda path: path.write_text("not a database\n"), "not a COLMAP database (not an SQLite file)"),
    "NaN keypoints": (_sql("UPDATE keypoints SET data = ? WHERE image_id = 1",
                           (np.full((70, 2), np.nan, np.float32).tobytes(),)), "70 point(s) not finite"),
    "unknown image ids": (_sql("UPDATE matches SET pair_id = pair_id + 1000"),
                          "matches between images v_boat/1.ppm and v_boat/2.ppm"),
    "a deleted image": (_sql("DELETE FROM images WHERE image_id = 2"),
                        "an image named v_boat/2.ppm, which the database lacks"),
}


@pytest.mark.parametrize("case", list(COLMAP_CASES))
def test_hostile_colmap_databases_are_one_line(root, tmp_path, case):
    change, says = COLMAP_CASES[case]
    path = database(tmp_path, root)
    change(path)
    select = ["hpatches", "--root", root, "--sequences", "v_boat", "--limit", 1]
    line = one_line_error(invoke("import", *select, "--out", tmp_path / "run", "--colmap", path))
    assert says in line and (str(path) in line or "v_boat/1-2" in line), line
    assert not (tmp_path / "run" / "per_pair.csv").exists()


def test_nan_geometries_do_not_reach_the_score(root, tmp_path):
    """The import reads the matches; the database's two-view geometries are COLMAP's, not scored."""
    path = database(tmp_path, root)
    _sql("UPDATE two_view_geometries SET H = ?", (np.full((3, 3), np.nan).tobytes(),))(path)
    select = ["hpatches", "--root", root, "--sequences", "v_boat", "--limit", 1]
    assert invoke("import", *select, "--out", tmp_path / "run", "--colmap", path).exit_code == 0
    assert pd.read_csv(tmp_path / "run" / "per_pair.csv")["mma@1"].iloc[0] == 1.0


def _replace(file, where, **dataset):
    del file[where]
    file.create_dataset(where, **dataset)


KEYPOINTS, MATCHES = "v_boat/2.ppm/keypoints", "v_boat-1.ppm/v_boat-2.ppm/matches0"
HUGE = dict(shape=(2_000_000_000, 2), dtype="f4", chunks=(1024, 2))  # no storage allocated: a small file
HLOC_CASES = {
    "keypoints N x 3": ("features", KEYPOINTS, dict(data=np.zeros((70, 3), np.float32)), "has shape (70, 3), expected N x 2"),
    "keypoints 2e9 rows": ("features", KEYPOINTS, HUGE, "declares shape (2000000000, 2)"),
    "keypoints bytes": ("features", KEYPOINTS, dict(data=np.array([b"x"] * 70)), "expected real numbers, got bytes"),
    "matches 2e9 rows": ("matches", MATCHES, dict(shape=(2_000_000_000,), dtype="i8", chunks=(4096,)),
                         "declares shape (2000000000,)"),
    "matches floats": ("matches", MATCHES, dict(data=np.full(70, 0.5)), "expected integer indices, got floats"),
    "matches N x 2": ("matches", MATCHES, dict(data=np.zeros((70, 2), np.int64)), "expected one index per keypoint"),
    "matches out of range": ("matches", MATCHES, dict(data=np.full(70, 10**6)), "not -1 (no match) nor an index"),
}


@pytest.mark.parametrize("case", list(HLOC_CASES))
def test_hostile_hloc_files_are_one_line(root, tmp_path, case):
    which, where, dataset, says = HLOC_CASES[case]

    def change(features, matches, folder):
        _replace(features if which == "features" else matches, where, **dataset)

    features, matches = hloc_files(tmp_path, root, change)
    select = ["hpatches", "--root", root, "--sequences", "v_boat", "--limit", len(PAIRS)]
    line = one_line_error(invoke("import", *select, "--out", tmp_path / "run", "--hloc", features, matches))
    named = features if which == "features" else matches
    assert f"{named}:" in line and says in line, line
    assert not (tmp_path / "run" / "per_pair.csv").exists()


@pytest.mark.parametrize("where, dataset, says", [
    ("v_boat/5.ppm/keypoints0", HUGE, "declares shape (2000000000, 2)"),
    ("v_boat/5.ppm/keypoints1", dict(data=np.zeros((5, 2))), "not -1 (no match) nor an index into the 5 keypoints"),
])
def test_hostile_gluefactory_files_are_one_line(root, tmp_path, where, dataset, says):
    path = gluefactory_file(tmp_path, root, lambda file, folder: _replace(file, where, **dataset))
    select = ["hpatches", "--root", root, "--sequences", "v_boat", "--limit", len(PAIRS)]
    line = one_line_error(invoke("import", *select, "--out", tmp_path / "run", "--gluefactory", path))
    assert f"{path}:" in line and says in line, line
    assert not (tmp_path / "run" / "per_pair.csv").exists()
