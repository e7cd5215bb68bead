"""`import --colmap`: every array a COLMAP database declares (keypoints, descriptors, matches,
two-view geometries) is checked against its bytes and a row bound before pycolmap allocates
it; a database declaring 2e9 match rows is one line, not a 16 GB allocation."""

from __future__ import annotations

import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from helpers import invoke, one_line_error

pycolmap = pytest.importorskip("pycolmap", reason="the COLMAP format needs pycolmap (the colmap extra)")


@pytest.fixture(scope="module")
def boat(shared_data) -> tuple[Path, list[str]]:
    root = shared_data / "hpatches-sequences-release"
    return root, ["hpatches", "--root", root, "--sequences", "v_boat", "--limit", 1]


def database(folder: Path, root: Path) -> Path:
    """A COLMAP database for v_boat (1, 2): a grid on image 1 matched to its true image on
    image 2 (corner convention), with descriptors and a two-view geometry."""
    grid = np.stack(np.meshgrid(np.arange(100, 700, 60.0), np.arange(100, 500, 60.0)), -1).reshape(-1, 2)
    H = np.loadtxt(root / "v_boat" / "H_1_2")
    warped = np.c_[grid, np.ones(len(grid))] @ H.T
    points = {"v_boat/1.ppm": grid, "v_boat/2.ppm": warped[:, :2] / warped[:, 2:]}
    path = folder / "database.db"
    db = pycolmap.Database.open(str(path))
    try:
        camera = db.write_camera(pycolmap.Camera(model="SIMPLE_RADIAL", width=850, height=680, params=[1000, 425, 340, 0]))
        ids = {name: db.write_image(pycolmap.Image(name=name, camera_id=camera)) for name in points}
        for name, k in points.items():
            db.write_keypoints(ids[name], (k + 0.5).astype(np.float32))
            db.write_descriptors(ids[name], pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT,
                                                                        np.zeros((len(k), 128), np.uint8)))
        pairs = np.stack([np.arange(len(grid))] * 2, axis=1).astype(np.uint32)
        db.write_matches(ids["v_boat/1.ppm"], ids["v_boat/2.ppm"], pairs)
        geometry = pycolmap.TwoViewGeometry()
        geometry.inlier_matches = pairs
        geometry.config = pycolmap.TwoViewGeometryConfiguration.PLANAR
        geometry.H = H
        db.write_two_view_geometry(ids["v_boat/1.ppm"], ids["v_boat/2.ppm"], geometry)
    finally:
        db.close()
    return path


def declare(path: Path, table: str, rows: int) -> None:
    """Set the declared row count of `table`'s first row, its bytes left as they are."""
    connection = sqlite3.connect(path)  # closed here: COLMAP's databases are in WAL mode
    try:
        with connection:
            changed = connection.execute(f"UPDATE {table} SET rows = ? WHERE rowid = (SELECT min(rowid) FROM {table})",
                                         (rows,)).rowcount
    finally:
        connection.close()
    assert changed == 1


def test_the_control_database_imports_and_scores(boat, tmp_path):
    root, select = boat
    assert invoke("import", *select, "--out", tmp_path / "run", "--colmap", database(tmp_path, root)).exit_code == 0
    rows = pd.read_csv(tmp_path / "run" / "per_pair.csv")
    assert len(rows) == 1 and rows["mma@1"].iloc[0] == 1.0


@pytest.mark.parametrize("table, rows, says", [
    ("matches", 2_000_000_000, "table matches, images v_boat/1.ppm and v_boat/2.ppm, declares 2000000000 x 2 entries"),
    ("keypoints", 2_000_000_000, "table keypoints, image v_boat/1.ppm, declares 2000000000 x 2 entries"),
    ("descriptors", 2_000_000_000, "table descriptors, image v_boat/1.ppm, declares 2000000000 x 128 entries"),
    ("two_view_geometries", 2_000_000_000, "table two_view_geometries, images v_boat/1.ppm and v_boat/2.ppm"),
    ("matches", 71, "table matches, images v_boat/1.ppm and v_boat/2.ppm, declares 71 x 2 entries and holds 560 "
                    "bytes; a damaged row"),
    ("keypoints", -1, "table keypoints, image v_boat/1.ppm, declares -1 x 2 entries"),
])
def test_a_declared_size_the_bytes_do_not_hold_is_refused_before_reading(boat, tmp_path, table, rows, says):
    root, select = boat
    path = database(tmp_path, root)
    declare(path, table, rows)
    line = one_line_error(invoke("import", *select, "--out", tmp_path / "run", "--colmap", path))
    assert f"{path}: {says}" in line and "refused before reading it" in line
    assert not (tmp_path / "run" / "per_pair.csv").exists()


def test_two_billion_match_rows_cost_no_memory(boat, tmp_path):
    """The command in a process limited to 6 GiB of address space (the 16 GB the 2e9 rows would
    take cannot be had): one line, no bad_alloc."""
    root, select = boat
    path = database(tmp_path, root)
    declare(path, "matches", 2_000_000_000)
    args = [str(a) for a in ("import", *select, "--out", tmp_path / "run", "--colmap", path)]
    code = ("import resource, sys; resource.setrlimit(resource.RLIMIT_AS, (6 << 30, 6 << 30)); "
            "from e3cm_bench.__main__ import main; sys.argv = ['e3cm-bench', *sys.argv[1:]]; main()")
    done = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=300)
    assert done.returncode == 2, done.stderr
    assert "declares 2000000000 x 2 entries" in done.stderr and "bad_alloc" not in done.stderr


def test_a_database_with_changes_left_in_its_wal_file_is_refused(boat, tmp_path):
    """COLMAP keeps its database in WAL mode: changes not yet written back sit in database.db-wal,
    which neither the copy read nor the sha256 recorded would hold."""
    root, select = boat
    path = database(tmp_path, root)
    connection = sqlite3.connect(path)
    try:
        with connection:
            connection.execute("CREATE TABLE note (x)")
        assert Path(f"{path}-wal").stat().st_size > 0
        line = one_line_error(invoke("import", *select, "--out", tmp_path / "run", "--colmap", path))
    finally:
        connection.close()
    assert f"{path}-wal" in line and "not yet written into" in line
