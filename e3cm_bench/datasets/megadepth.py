"""MegaDepth-1500 in either layout it is distributed in.

- LoFTR's: ``ROOT/scene_info/*.npz`` pair lists, image paths relative to ROOT (the protocol's).
- glue-factory's ``megadepth1500.zip``: ``ROOT/views.txt`` (one line per image:
  ``name R(9) t(3) MODEL width height params``, R, t world-to-camera, COLMAP's camera),
  ``ROOT/pairs.txt`` (``name0 name1`` per line), images under ``ROOT/images/``.

Both give the same pairs from the same numbers: the intrinsics are COLMAP's in both (a
principal point of width/2 is COLMAP's corner convention) and are used as they are, as the
protocol does with LoFTR's lists; T_0to1 = T1 @ inv(T0) for world-to-camera poses.
"""

from __future__ import annotations

import io
import pickle
import zipfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from e3cm_bench.datasets.base import DatasetError, Pair, PairList, name_pairs, require_directory, text_lines
from e3cm_bench.datasets.truth import check_image_size, check_intrinsics, check_pose, check_world_pose

SCENE_INFO_KEYS = ("image_paths", "intrinsics", "poses", "pair_infos")


class MegaDepth1500(PairList):
    """Pairs from every ``root/scene_info/*.npz`` (sorted), or from the ``scene_info`` paths given,
    or, where ROOT holds glue-factory's layout instead (``views.txt``, ``pairs.txt``; also
    found in ``ROOT/megadepth1500``), from its pair list in its order.

    Each npz holds per-image ``image_paths`` (relative to root, None for unused images),
    ``intrinsics`` (3x3), ``poses`` (world-to-camera 4x4) and ``pair_infos``, entries
    ``((i, j), overlap, central_matches)``. T_0to1 = poses[j] @ inv(poses[i]).
    """

    name = "megadepth"

    def __init__(
        self,
        root: str | Path,
        scene_info: Sequence[str | Path] | None = None,
        skip_bad: bool = False,
    ) -> None:
        self.root = require_directory(root, "MegaDepth")
        self.layout = "loftr"
        if scene_info is None and not (self.root / "scene_info").is_dir():
            found = gluefactory_folder(self.root)
            if found is None:
                raise DatasetError(f"{self.root}: holds neither scene_info/*.npz (LoFTR's MegaDepth-1500 layout) "
                                   "nor views.txt and pairs.txt (glue-factory's megadepth1500)")
            self.layout, self.root, self.scene_info = "gluefactory", found, []
            pairs, bad = read_gluefactory(found)
            super().__init__(pairs, found / GLUEFACTORY_PAIRS, skip_bad, bad)
            return
        if scene_info is None:
            self.scene_info = sorted((self.root / "scene_info").glob("*.npz"))
            if not self.scene_info:
                raise DatasetError(f"{self.root / 'scene_info'}: no *.npz scene_info files")
        else:
            self.scene_info = [Path(p) for p in scene_info]
        pairs, bad = [], []
        for path in self.scene_info:
            good, wrong = self._read_scene_info(path)
            pairs += good
            bad += wrong
        # Name the one file when there is one; otherwise the folder the lists usually live in.
        source = self.scene_info[0] if len(self.scene_info) == 1 else self.root / "scene_info"
        super().__init__(pairs, source, skip_bad, bad)

    def _read_scene_info(self, path: Path) -> tuple[list[Pair], list[tuple[str, str]]]:
        """The file's pairs, and (name, problem) of those whose ground truth is unusable."""
        scene = load_scene_info(path)
        image_paths = scene["image_paths"]
        pairs, bad = [], []
        for index, info in enumerate(scene["pair_infos"]):
            i, j = _image_indices(info, len(image_paths), path, index)
            for image_index in (i, j):
                if image_paths[image_index] is None:
                    raise DatasetError(
                        f"{path}: pair_infos[{index}] uses image {image_index}, which has no path"
                    )
            image0 = self.root / str(image_paths[i])
            image1 = self.root / str(image_paths[j])
            name = f"{path.stem}/{image0.stem}--{image1.stem}"
            try:
                K0 = _matrix(scene["intrinsics"][i], (3, 3), path, f"intrinsics[{i}]")
                K1 = _matrix(scene["intrinsics"][j], (3, 3), path, f"intrinsics[{j}]")
                check_intrinsics(K0, f"{path}: intrinsics[{i}]")
                check_intrinsics(K1, f"{path}: intrinsics[{j}]")
                pose0 = _matrix(scene["poses"][i], (4, 4), path, f"poses[{i}]")
                pose1 = _matrix(scene["poses"][j], (4, 4), path, f"poses[{j}]")
                check_world_pose(pose0, f"{path}: poses[{i}]")
                check_world_pose(pose1, f"{path}: poses[{j}]")
                T_0to1 = _relative_pose(pose0, pose1, path, i)
                check_pose(T_0to1, f"{path}: pair_infos[{index}] (poses[{i}], poses[{j}])")
            except DatasetError as error:
                bad.append((name, str(error)))
                continue
            pairs.append(Pair(name=name, image0=image0, image1=image1, K0=K0, K1=K1, T_0to1=T_0to1,
                              scene=path.stem))
        return pairs, bad

    def settings(self) -> dict:
        if self.layout == "gluefactory":
            return {"dataset": self.name, "root": str(self.root), "layout": self.layout,
                    "views": str(self.root / GLUEFACTORY_VIEWS), "pairs": str(self.root / GLUEFACTORY_PAIRS)}
        return {
            "dataset": self.name,
            "root": str(self.root),
            "scene_info": [str(p) for p in self.scene_info],
        }


GLUEFACTORY_VIEWS, GLUEFACTORY_PAIRS, GLUEFACTORY_SCENE = "views.txt", "pairs.txt", "megadepth1500"
# COLMAP camera models whose parameters start with the pinhole ones; any further parameters are
# distortion, which must be zero (MegaDepth's images are undistorted) for K to describe the camera.
PINHOLE_PARAMS = {"PINHOLE": 4, "SIMPLE_PINHOLE": 3, "SIMPLE_RADIAL": 3, "RADIAL": 3, "OPENCV": 4}


def gluefactory_folder(root: Path) -> Path | None:
    """ROOT, or ROOT/megadepth1500, where it holds glue-factory's views.txt and pairs.txt."""
    for folder in (root, root / GLUEFACTORY_SCENE):
        if (folder / GLUEFACTORY_VIEWS).is_file() and (folder / GLUEFACTORY_PAIRS).is_file():
            return folder
    return None


def read_gluefactory(folder: Path) -> tuple[list[Pair], list[tuple[str, str]]]:
    """The pairs of glue-factory's megadepth1500 folder in pairs.txt's order, and (name, problem)
    of those whose ground truth is unusable. Names are ``megadepth1500/<stem0>--<stem1>``."""
    views = _read_views(folder / GLUEFACTORY_VIEWS)
    pairs_path = folder / GLUEFACTORY_PAIRS
    pairs, bad = [], []
    for number, *names in name_pairs(pairs_path, views, "which views.txt does not list"):
        (K0, T0, problem0), (K1, T1, problem1) = views[names[0]], views[names[1]]
        image0, image1 = folder / "images" / names[0], folder / "images" / names[1]
        name = f"{GLUEFACTORY_SCENE}/{image0.stem}--{image1.stem}"
        try:
            for problem in (problem0, problem1):
                if problem:
                    raise DatasetError(problem)
            T_0to1 = T1 @ np.linalg.inv(T0)
            check_pose(T_0to1, f"{pairs_path}: line {number}")
        except DatasetError as error:
            bad.append((name, str(error)))
            continue
        pairs.append(Pair(name=name, image0=image0, image1=image1, K0=K0, K1=K1, T_0to1=T_0to1,
                          scene=GLUEFACTORY_SCENE))
    return pairs, bad


def _read_views(path: Path) -> dict[str, tuple]:
    """name -> (K, world-to-camera 4x4, problem or ""); a line that cannot be parsed is an error."""
    views = {}
    for number, line in text_lines(path):
        fields = line.split()
        where = f"{path}: line {number}"
        if len(fields) < 16:
            raise DatasetError(f"{where} holds {len(fields)} fields; expected name R(9) t(3) MODEL width height params")
        name, model = fields[0], fields[13]
        try:
            numbers = np.array(fields[1:13] + fields[16:], dtype=np.float64)
        except ValueError:
            raise DatasetError(f"{where}: a pose or camera value is not a number") from None
        if not np.all(np.isfinite(numbers)):
            raise DatasetError(f"{where}: non-finite pose or camera values")
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = numbers[:9].reshape(3, 3), numbers[9:12]
        params, problem = numbers[12:], _view_problem(T, fields[14:16], f"{where}: view {name}")
        n = PINHOLE_PARAMS.get(model)
        if problem:
            K = np.eye(3)
        elif n is None or len(params) < n:
            problem = f"{where}: camera model {model} with {len(params)} parameters is not a pinhole camera"
            K = np.eye(3)
        else:
            fx, fy, cx, cy = params[:4] if n == 4 else (params[0], params[0], params[1], params[2])
            K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
            if np.any(params[n:] != 0):
                problem = f"{where}: camera {model} has non-zero distortion; MegaDepth's images are undistorted"
            else:
                try:
                    check_intrinsics(K, f"{where}: view {name}")
                except DatasetError as error:
                    problem = str(error)
        if name in views:
            raise DatasetError(f"{where}: view {name} is listed twice")
        views[name] = (K, T, problem)
    if not views:
        raise DatasetError(f"{path}: lists no views")
    return views


def _view_problem(T: np.ndarray, size: list[str], where: str) -> str:
    """What the ground-truth rule (truth.py) finds wrong with a view's pose and image size, or ""."""
    try:
        check_world_pose(T, where)
        try:
            width, height = float(size[0]), float(size[1])
        except ValueError:
            width = height = float("nan")
        check_image_size(width, height, where)
    except DatasetError as error:
        return str(error)
    return ""


# What a scene_info pickle may build: numpy arrays, dtypes and scalars (module paths of numpy
# 1 and 2). Anything else (a function to call, an object with a custom __reduce__) is refused
# before it is built, so a crafted file cannot run code.
SAFE_PICKLE_GLOBALS = {
    ("numpy", "ndarray"), ("numpy", "dtype"),
    ("numpy.core.multiarray", "_reconstruct"), ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "scalar"),
}


class _ArraysOnlyUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str):
        if (module, name) in SAFE_PICKLE_GLOBALS or (module.startswith("numpy.dtypes") and name.endswith("DType")):
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"it would build {module}.{name}; only numpy arrays and plain containers are read")


# The most one scene_info member may hold once decompressed. The LoFTR lists' largest member
# is a few MiB; a full MegaDepth scene's (depth paths, overlap matrix) stays under 256 MiB.
MAX_MEMBER_BYTES = 1 << 30


def _read_npz_members(path: Path) -> dict:
    """The SCENE_INFO_KEYS members of an npz archive, and only those: the others (a depth map
    list, an overlap matrix, or a 2 GB member of a crafted file) are never decompressed. Each
    member's size as the archive declares it is checked before it is read."""
    loaded = {}
    with zipfile.ZipFile(path) as archive:
        for member in archive.infolist():
            key = member.filename.removesuffix(".npy")
            if key not in SCENE_INFO_KEYS or key in loaded:
                continue
            if member.file_size > MAX_MEMBER_BYTES:
                raise ValueError(f"member {member.filename} declares {member.file_size / 2**20:.0f} MiB, over the "
                                 f"{MAX_MEMBER_BYTES >> 20} MiB a scene_info member may hold")
            # zipfile stops reading at the declared size, so the bound holds for what is read too
            loaded[key] = _read_npy(archive.read(member))
    return loaded


def _read_npy(data: bytes) -> np.ndarray:
    """One .npy member of an archive; object arrays (pickled inside) go through the safe unpickler."""
    f = io.BytesIO(data)
    version = np.lib.format.read_magic(f)
    read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
    _, _, dtype = read_header(f)
    if not dtype.hasobject:
        return np.lib.format.read_array(io.BytesIO(data), allow_pickle=False)
    array = _ArraysOnlyUnpickler(f).load()
    if not isinstance(array, np.ndarray):
        raise pickle.UnpicklingError("an object array member holds something else")
    return array


def load_scene_info(path: Path) -> dict:
    """The four arrays of a scene_info file; an unreadable or incomplete one is a DatasetError.

    The LoFTR MegaDepth-1500 lists are pickled dicts despite their .npz suffix; lists written
    with np.savez are real npz archives. Archives load with pickles refused; pickles load
    through an unpickler that builds numpy arrays and plain containers only.
    """
    if not path.is_file():
        raise DatasetError(f"{path}: scene_info file not found")
    try:
        if zipfile.is_zipfile(path):
            loaded = _read_npz_members(path)
        else:
            with open(path, "rb") as f:
                loaded = _ArraysOnlyUnpickler(f).load()
    except (OSError, ValueError, EOFError, pickle.UnpicklingError, zipfile.BadZipFile) as error:
        reason = " ".join(str(error).split())
        raise DatasetError(f"{path}: not a readable scene_info file ({reason})") from None
    if not isinstance(loaded, dict):
        raise DatasetError(f"{path}: expected an npz archive or a pickled dict")
    missing = [key for key in SCENE_INFO_KEYS if key not in loaded]
    if missing:
        raise DatasetError(f"{path}: scene_info lacks the key(s) {', '.join(missing)}")
    scene = {key: loaded[key] for key in SCENE_INFO_KEYS}
    try:
        _measure(scene, 0, {}, set())
    except ValueError as error:
        raise DatasetError(f"{path}: not a scene_info file ({error})") from None
    return _one_per_image(scene, path)


# What a scene_info can hold, counted as its values would be expanded (a list that holds one
# list twice counts it twice: np.asarray copies it twice): a pair_infos entry is ((i, j),
# overlap, central_matches), an intrinsics entry 3x3; a full MegaDepth scene's lists come to a
# few million entries and a few hundred MB. A crafted 2.7 KB pickle of a list that holds the
# same list twice, 30 levels deep, would expand to 2**30 entries: refused before anything uses it.
MAX_DEPTH = 12
MAX_ENTRIES = 20_000_000
MAX_EXPANDED_BYTES = 2 << 30


def _measure(value, depth: int, seen: dict, open_: set) -> tuple[int, int]:
    """(entries, bytes) of `value` expanded; a ValueError beyond MAX_DEPTH, MAX_ENTRIES or
    MAX_EXPANDED_BYTES, or for a value that holds itself. Each object is measured once."""
    if depth > MAX_DEPTH:
        raise ValueError(f"nested deeper than the {MAX_DEPTH} levels a scene_info has")
    if isinstance(value, np.ndarray) and not value.dtype.hasobject:
        return 1, value.nbytes
    if not isinstance(value, (list, tuple, dict, np.ndarray)):
        return 1, 64
    key = (id(value), depth)  # by depth too: the depth bound holds for each place an object is met
    if key in seen:
        return seen[key]
    if id(value) in open_:
        raise ValueError("a value that holds itself")
    open_.add(id(value))
    entries, size = 1, 0
    for item in (
        value.values() if isinstance(value, dict) else value.ravel() if isinstance(value, np.ndarray) else value
    ):
        n, b = _measure(item, depth + 1, seen, open_)
        entries, size = entries + n, size + b
        if entries > MAX_ENTRIES or size > MAX_EXPANDED_BYTES:
            raise ValueError(f"it expands to over {MAX_ENTRIES:,} values or {MAX_EXPANDED_BYTES >> 30} GiB")
    open_.discard(id(value))
    seen[key] = (entries, size)
    return entries, size


def _one_per_image(scene: dict, path: Path) -> dict:
    """The scene, where intrinsics and poses have one entry per image path; a DatasetError otherwise."""
    try:
        lengths = {key: len(scene[key]) for key in ("image_paths", "intrinsics", "poses")}
    except TypeError:
        raise DatasetError(f"{path}: image_paths, intrinsics and poses must be lists (one entry per image)") from None
    for key in ("intrinsics", "poses"):
        if lengths[key] < lengths["image_paths"]:
            raise DatasetError(f"{path}: {key} has {lengths[key]} entries for {lengths['image_paths']} images "
                               "(image_paths); a scene_info has one per image")
    return scene


def _image_indices(info, n_images: int, path: Path, index: int) -> tuple[int, int]:
    try:
        i, j = (int(v) for v in info[0])
    except (TypeError, ValueError, IndexError):
        raise DatasetError(
            f"{path}: pair_infos[{index}] is not ((i, j), overlap, central_matches)"
        ) from None
    if not (0 <= i < n_images and 0 <= j < n_images):
        raise DatasetError(
            f"{path}: pair_infos[{index}] = ({i}, {j}) is out of range for {n_images} images"
        )
    return i, j


def _matrix(value, shape: tuple[int, int], path: Path, what: str) -> np.ndarray:
    try:
        matrix = np.asarray(value, dtype=np.float64).reshape(shape)
    except (TypeError, ValueError):
        raise DatasetError(f"{path}: {what} is not a {shape[0]}x{shape[1]} matrix") from None
    if not np.all(np.isfinite(matrix)):
        raise DatasetError(f"{path}: {what} has non-finite entries")
    return matrix


def _relative_pose(world_to_cam0: np.ndarray, world_to_cam1: np.ndarray, path: Path, i: int):
    """Camera 0 to camera 1: T_0to1 = P1 @ inv(P0) for world-to-camera poses P."""
    try:
        return world_to_cam1 @ np.linalg.inv(world_to_cam0)
    except np.linalg.LinAlgError:
        raise DatasetError(f"{path}: poses[{i}] is singular") from None
