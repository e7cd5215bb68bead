"""A COLMAP database (``database.db``), written and read through pycolmap, PyPI's COLMAP
bindings (the ``colmap`` extra; 4.2.1 is the version tested: its ``Database`` class writes
cameras, images, keypoints, matches and two-view geometries, so no SQL is written here).

COLMAP's keypoints are in its corner convention: the top-left pixel's centre is (0.5, 0.5)
(hloc adds 0.5 when it imports into COLMAP: hloc/triangulation.py ``keypoints += 0.5  #
COLMAP origin``). COLMAP stores them as float32, so half a pixel added to a float32 can lose
its last bit where the sum crosses a power of two (x in [2^k - 0.5, 2^k)); docs/interchange.md
gives what that changes.

Export, per image: a camera (PINHOLE from the pair's intrinsics where the benchmark has them,
the principal point moved by half a pixel with the keypoints; else SIMPLE_RADIAL with COLMAP's
own prior, focal 1.2 x the longer side), its name (path relative to the dataset root), and one
keypoint list holding the matched keypoints of every pair it is in, each location once
(tracks.py says why and how a radius merges near ones). Per pair:
the matches, and a two-view geometry holding the inliers of the evaluation's own estimate (pose:
the essential-matrix RANSAC's inliers, CALIBRATED, with E and the relative pose; homography:
the matches within the RANSAC threshold of the estimated H, PLANAR, with H), so that COLMAP's
mapper can run without its own verification. A pair whose estimate failed gets no geometry.
"""

from __future__ import annotations

import shutil
import sqlite3
import tempfile
from pathlib import Path

import numpy as np

from e3cm_bench.ground.files import file_sha256, write_atomically
from e3cm_bench.ground.matches import Matches, MatchesError
from e3cm_bench.interchange.base import (
    MAX_POINTS,
    MissingPair,
    source_identity,
    check_declared,
    image_name,
    real_points,
)
from e3cm_bench.ground.pycolmap import pycolmap_module
from e3cm_bench.interchange.pixels import from_origin, resolve_origin, to_origin
from e3cm_bench.interchange.registry import Format, register



@register
class ColmapFormat(Format):
    name = "colmap"
    origin = "corner"
    reads = ("DATABASE.db",)
    import_help = "A COLMAP database.db (images named by their path under the root; needs pycolmap)."
    writes = "database.db"
    outputs = ("database.db",)
    merges = True
    stores_geometry = True
    labelled_by = "database"

    def source(self, paths, benchmark: str, origin: str | None = None):
        return ColmapSource(*paths, origin=origin)

    def write(self, out: Path, items: list, origin: str, job) -> list[Path]:
        return write_colmap(out, items, origin, job.merge_px, merged=job.merged)

    def check_available(self) -> None:
        pycolmap_module()


def verify_pairs(pycolmap, database: Path, pairs, options) -> None:
    """COLMAP's geometric verification of `pairs` ((name0, name1) of images in `database`): each
    pair's matches through pycolmap.estimate_two_view_geometry, the estimator verify_matches runs,
    and the two-view geometry written back. verify_matches reads its pairs from a text file whose
    lines it splits at spaces, so an image named 'a b.png' became 'a' and every pair failed
    silently; here names are never written as text."""
    with pycolmap.Database.open(str(database)) as db:
        images = {image.name: image for image in db.read_all_images()}
        cameras = {camera.camera_id: camera for camera in db.read_all_cameras()}
        keypoints: dict[int, np.ndarray] = {}

        def points(image) -> np.ndarray:
            if image.image_id not in keypoints:
                keypoints[image.image_id] = np.asarray(db.read_keypoints(image.image_id), np.float64)[:, :2]
            return keypoints[image.image_id]

        for name0, name1 in pairs:
            image0, image1 = images[name0], images[name1]
            if not db.exists_matches(image0.image_id, image1.image_id):
                continue
            matches = np.asarray(db.read_matches(image0.image_id, image1.image_id), np.uint32)
            geometry = pycolmap.estimate_two_view_geometry(cameras[image0.camera_id], points(image0),
                                                           cameras[image1.camera_id], points(image1), matches, options)
            if db.exists_two_view_geometry(image0.image_id, image1.image_id):
                db.delete_two_view_geometry(image0.image_id, image1.image_id)
            db.write_two_view_geometry(image0.image_id, image1.image_id, geometry)


def _shift(origin: str) -> float:
    return float(to_origin(np.zeros((1, 2)), origin)[0, 0])


def mapper_options(pycolmap, calibrated: bool = True):
    """pycolmap's incremental mapper options under which an export is checked (tests,
    scripts/results/mapper_on_export.py): one thread and seed 0, so that the same database gives the
    same model; with ``calibrated``, the cameras' intrinsics held fixed, since the benchmark's
    calibration is ground truth (refining the focal length of a forward-moving camera is what
    makes COLMAP's default lose most of KITTI: docs/interchange.md)."""
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = options.mapper.num_threads = 1
    options.random_seed = options.mapper.random_seed = 0
    if calibrated:
        options.ba_refine_focal_length = options.ba_refine_principal_point = options.ba_refine_extra_params = False
    return options


def camera_for(pycolmap, K: np.ndarray | None, size: tuple[int, int], origin: str):
    w, h = (int(v) for v in size)
    if K is None:
        f = 1.2 * max(w, h)  # COLMAP's default focal prior for an image without EXIF
        return pycolmap.Camera(model="SIMPLE_RADIAL", width=w, height=h, params=[f, w / 2, h / 2, 0.0])
    K = np.asarray(K, np.float64)
    shift = _shift(origin)
    # has_prior_focal_length: the focal is the benchmark's calibration, not a guess, so that
    # COLMAP verifies the pair with an essential matrix and its mapper keeps the intrinsics
    return pycolmap.Camera(
        model="PINHOLE",
        width=w,
        height=h,
        params=[K[0, 0], K[1, 1], K[0, 2] + shift, K[1, 2] + shift],
        has_prior_focal_length=True,
    )


def write_colmap(out: Path, items, origin: str | None = None, merge_px: float = 0.0, merged=None,
                 cameras=None) -> list[Path]:
    """database.db in OUT for base.ExportItem's: one keypoint list per image, a location that
    several pairs matched written once (tracks.merge_keypoints, with merge_px), so that the
    mapper can chain pairs into tracks of more than two views. merged: merge_keypoints' result
    for these items, where the caller has it. cameras: image name -> the pycolmap.Camera it gets
    instead of camera_for's (images given the same object share one camera, as COLMAP's
    single_camera makes them)."""
    origin = resolve_origin(ColmapFormat, origin)
    from e3cm_bench.interchange.tracks import merge_keypoints

    pycolmap = pycolmap_module()
    shift = _shift(origin)
    keypoints, indices = merged or merge_keypoints(
        ((item.name0, item.name1, item.matches.keypoints0, item.matches.keypoints1) for item in items), merge_px)

    def write(tmp: Path) -> None:
        tmp.unlink()  # pycolmap creates the file itself
        db = pycolmap.Database.open(str(tmp))
        try:
            ids: dict[str, int] = {}
            written: dict[int, int] = {}  # id() of a given camera -> its camera_id, for those shared
            for item in items:
                for name, K, size in ((item.name0, item.K0, item.size0), (item.name1, item.K1, item.size1)):
                    if name not in ids:
                        given = (cameras or {}).get(name)
                        camera_id = (db.write_camera(camera_for(pycolmap, K, size, origin)) if given is None
                                     else _shared_camera(db, written, given))
                        ids[name] = db.write_image(pycolmap.Image(name=name, camera_id=camera_id))
            for name, points in keypoints.items():
                db.write_keypoints(ids[name], to_origin(points, origin).astype(np.float32).reshape(-1, 2))
            for item, pairs in zip(items, indices):
                id0, id1 = ids[item.name0], ids[item.name1]
                if db.exists_matches(id0, id1):
                    raise ValueError(f"two pairs of the run join images {item.name0} and {item.name1}; "
                                     "COLMAP holds one match list per image pair")
                pairs = pairs.astype(np.uint32)
                db.write_matches(id0, id1, pairs)
                if item.geometry is not None:
                    db.write_two_view_geometry(id0, id1, _two_view_geometry(pycolmap, item.geometry, pairs, shift))
        finally:
            db.close()

    try:
        return [write_atomically(out / "database.db", write)]
    except RuntimeError as error:  # pycolmap's own words for a database it could not open or write
        for left in Path(out).glob(".database.db.*.tmp-*"):  # SQLite's -wal and -shm of the temporary file
            left.unlink(missing_ok=True)
        raise _unwritten(out / "database.db", error) from None


def _two_view_geometry(pycolmap, geometry: dict, pairs: np.ndarray, shift: float):
    """A pair's verified geometry as COLMAP stores it: its inlier matches and H (PLANAR, moved to
    COLMAP's pixel origin) or E and the relative pose (CALIBRATED)."""
    tvg = pycolmap.TwoViewGeometry()
    tvg.inlier_matches = pairs[geometry["inliers"]]
    if "H" in geometry:
        T = np.array([[1, 0, shift], [0, 1, shift], [0, 0, 1]], np.float64)
        tvg.config = pycolmap.TwoViewGeometryConfiguration.PLANAR
        tvg.H = T @ geometry["H"] @ np.linalg.inv(T)
    else:
        R, t = geometry["R"], geometry["t"]
        tvg.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
        tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]], np.float64)
        tvg.E = tx @ R
        tvg.cam2_from_cam1 = pycolmap.Rigid3d(pycolmap.Rotation3d(R), t)
    return tvg


def _unwritten(path: Path, error: RuntimeError) -> Exception:
    """pycolmap says no more than "No registered database factory succeeded" for a full disk:
    an OSError (ENOSPC: the commands' one line for a full disk) where little space is left, else
    a ValueError naming the file and pycolmap's message."""
    import errno
    import shutil

    try:
        free = shutil.disk_usage(path.parent).free
    except OSError:
        free = None
    if free is not None and free < 16 << 20:
        return OSError(errno.ENOSPC, "No space left on device", str(path))
    return ValueError(f"{path}: pycolmap could not write the COLMAP database ({' '.join(str(error).split())[:200]})")


def _shared_camera(db, written: dict, camera) -> int:
    """The id of a caller's camera, written once: images given the same object share it (the
    objects live in the caller's mapping for the whole write, so their id() stays theirs)."""
    if id(camera) not in written:
        written[id(camera)] = db.write_camera(camera)
    return written[id(camera)]


# COLMAP's array tables: (table, key column, bytes per entry (descriptors: uint8 or float32),
# widths a row may have). Each row declares rows x cols, and COLMAP allocates that before it
# reads the blob: a row declaring 2e9 matches takes 16 GB whatever the blob holds.
BLOB_TABLES = (("keypoints", "image_id", (4,), (2, 4, 6)), ("descriptors", "image_id", (1, 4), None),
               ("matches", "pair_id", (4,), (2,)), ("two_view_geometries", "pair_id", (4,), (2,)))
PAIR_ID_BASE = 2147483647  # COLMAP's kMaxNumImages: pair_id = id1 * this + id2


def check_blob_sizes(copy: Path, database: Path) -> None:
    """Every array a COLMAP database declares, checked against its bytes and against MAX_POINTS
    rows before pycolmap allocates it (any table, read or not: pycolmap may touch them all).
    `copy`: the private copy read here; `database`: the user's file, named in the error."""
    try:
        connection = sqlite3.connect(f"file:{copy}?mode=ro", uri=True)
    except sqlite3.Error as error:
        raise ValueError(f"{database}: not a readable COLMAP database ({error})") from None
    try:
        tables = {row[0] for row in connection.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        for table, key, itemsizes, widths in BLOB_TABLES:
            if table not in tables:
                continue
            size = "coalesce(length(data), 0)"
            fits = " OR ".join(f"rows * cols * {n} = {size}" for n in itemsizes)
            wide = f" OR cols NOT IN ({', '.join(map(str, widths))})" if widths else ""
            bad = connection.execute(
                f"SELECT {key}, rows, cols, {size} FROM {table} WHERE rows < 0 OR cols < 0 OR rows > ? OR cols > 4096"
                f"{wide} OR NOT ({fits}) LIMIT 1", (MAX_POINTS,)).fetchone()
            if bad is not None:
                raise ValueError(
                    f"{database}: table {table}, {_row_name(connection, key, bad[0])}, declares "
                    f"{bad[1]} x {bad[2]} entries and holds {bad[3]} bytes; "
                    + (f"more rows than the {MAX_POINTS} an import reads" if bad[1] > MAX_POINTS else "a damaged row")
                    + ": refused before reading it"
                )
    except sqlite3.Error as error:
        raise ValueError(f"{database}: not a readable COLMAP database ({error})") from None
    finally:
        connection.close()


def _row_name(connection, key: str, value: int) -> str:
    """'image NAME' or 'images NAME0 and NAME1' for a row of an array table."""
    ids = [value] if key == "image_id" else [value // PAIR_ID_BASE, value % PAIR_ID_BASE]
    names = []
    for image_id in ids:
        found = connection.execute("SELECT name FROM images WHERE image_id = ?", (image_id,)).fetchone()
        names.append(found[0] if found else f"#{image_id}")
    return f"image {names[0]}" if len(names) == 1 else f"images {names[0]} and {names[1]}"


class ColmapSource:
    """A COLMAP database: images found by name (relative to the dataset root), keypoints in
    COLMAP's corner convention, the raw matches of each pair (not only the verified ones:
    they are what the matcher gave)."""

    format = "colmap"
    per_pair = False

    def __init__(self, database: Path, origin: str | None = None) -> None:
        self.database = Path(database)
        self.origin = resolve_origin(ColmapFormat, origin)
        if not self.database.is_file():
            raise ValueError(f"{self.database}: not found")
        with open(self.database, "rb") as f:
            if f.read(16) != b"SQLite format 3\x00":
                raise ValueError(f"{self.database}: not a COLMAP database (not an SQLite file)")
        self._db = None
        self._ids: dict[str, int] = {}

    def files(self, pairs) -> dict[str, str]:
        return {"database": file_sha256(self.database)}

    def identity(self, files: dict[str, str]) -> dict:
        return source_identity({"format": self.format, "files": files}, self.origin, ColmapFormat.origin)

    def location(self) -> dict:
        return {"database": str(self.database), "pixel_origin": self.origin}

    def expected(self, pair, root: Path) -> str:
        names = image_name(pair.image0, root), image_name(pair.image1, root)
        absent = [n for n in names if n not in self._ids]
        if absent:
            return f"{self.database}: an image named {absent[0]}, which the database lacks"
        return f"{self.database}: matches between images {names[0]} and {names[1]}"

    def _open(self):
        """The database, opened from a private copy: opening a file, COLMAP creates missing
        tables and upgrades old schemas in place, which would change the user's file (and its
        hash, the import's identity)."""
        if self._db is None:
            pycolmap = pycolmap_module()
            wal = Path(f"{self.database}-wal")
            if wal.is_file() and wal.stat().st_size:
                # what COLMAP has not yet written back: the copy and the sha256 would miss it
                raise ValueError(f"{self.database}: holds changes in {wal} not yet written into it (a COLMAP or "
                                 "sqlite3 still has it open?): close that program, then import")
            self._copy = Path(tempfile.mkdtemp(prefix="e3cm-colmap-")) / "database.db"
            try:
                shutil.copyfile(self.database, self._copy)
                check_blob_sizes(self._copy, self.database)
                self._db = pycolmap.Database.open(str(self._copy))
                self._ids = {image.name: image.image_id for image in self._db.read_all_images()}
            except ValueError:
                shutil.rmtree(self._copy.parent, ignore_errors=True)
                raise
            except Exception as error:  # pycolmap raises its own types for a damaged file
                shutil.rmtree(self._copy.parent, ignore_errors=True)
                raise ValueError(f"{self.database}: not a readable COLMAP database ({error})") from None
        return self._db

    def close(self) -> None:
        if self._db is not None:
            self._db.close()
            shutil.rmtree(self._copy.parent, ignore_errors=True)
            self._db = None

    def read(self, pair, root: Path) -> Matches:
        db = self._open()
        names = image_name(pair.image0, root), image_name(pair.image1, root)
        missing = [n for n in names if n not in self._ids]
        if missing:
            raise MissingPair(f"{self.database}: no image named {missing[0]}")
        id0, id1 = (self._ids[n] for n in names)
        if not db.exists_matches(id0, id1):
            raise MissingPair(f"{self.database}: no matches between {names[0]} and {names[1]}")
        points = []
        for name, image_id in zip(names, (id0, id1)):
            what = f"{self.database}: keypoints of {name}"
            check_declared(what, (db.num_keypoints_for_image(image_id), 2), 4)
            points.append(real_points(np.asarray(db.read_keypoints(image_id))[:, :2], what))
        index = np.asarray(db.read_matches(id0, id1), np.int64).reshape(-1, 2)
        for side, name in enumerate(names):
            past = index[:, side] >= len(points[side])
            if past.any():
                raise MatchesError(f"{self.database}: a match of {names[0]} and {names[1]} points to keypoint "
                                   f"{int(index[past, side][0])} of {name}, which has {len(points[side])}")
        k0 = from_origin(points[0][index[:, 0]], self.origin)
        k1 = from_origin(points[1][index[:, 1]], self.origin)
        return Matches(k0, k1, None)
