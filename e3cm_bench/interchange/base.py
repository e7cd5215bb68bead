"""What every format shares: the missing-pair error, image names, and the checks an array
read from another tool's file passes before it is used (its kind, its shape and its declared
size, checked before a byte of it is read; an HDF5 file, that it holds all its data itself)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

# h5py is imported in the functions that read or write HDF5: the command line imports this module
# for the format registry (registry.py) and answers without loading h5py.

from e3cm_bench.ground.matches import Matches, MatchesError

# The most keypoints (or match entries) one array may declare. A dense matcher at 4K gives a
# few million; a file declaring more is refused before it is read, so that a 37 KB file that
# declares gigabytes (compressed zeros) cannot take the memory (issue 44, finding 12).
MAX_POINTS = 4_000_000


class MissingPair(LookupError):
    """A benchmark pair the source holds no matches for."""


def image_name(path: Path, root: Path) -> str:
    """An image's name in another tool's file: its path relative to the dataset root, with '/'
    (hloc's and COLMAP's image names), else its file name."""
    path = Path(path).resolve()
    try:
        return path.relative_to(Path(root).resolve()).as_posix()
    except ValueError:
        return path.name


def source_identity(identity: dict, origin: str, default: str) -> dict:
    """A source's identity with its pixel origin, named only where it is not the format's own:
    identities recorded before --pixel-origin existed then stay equal, and a folder imported
    with them still resumes."""
    return {**identity, "pixel_origin": origin} if origin != default else identity


def check_declared(what: str, shape: tuple, itemsize: int) -> None:
    """Refuse an array whose declared shape is larger than MAX_POINTS rows (of any width)."""
    rows = int(shape[0]) if len(shape) else 1
    if rows > MAX_POINTS or int(np.prod(shape, dtype=np.int64)) > 8 * MAX_POINTS:
        size = int(np.prod(shape, dtype=np.int64)) * int(itemsize)
        raise MatchesError(f"{what} declares shape {tuple(shape)} ({size / 2**20:.0f} MiB); more than the "
                           f"{MAX_POINTS} rows an import reads")


def check_self_contained(path: Path) -> None:
    """Refuse an HDF5 file that reads anything from elsewhere or by another name: a soft or
    external link, or a dataset whose values live outside the file (a virtual dataset, or
    external raw storage). hloc and glue-factory write none of these (h5py's create_group and
    create_dataset make hard links to data stored in the file). Followed, they would read a
    pair from a file the import's identity (the named file's sha256) never hashed, read a
    virtual dataset whose source is missing as its fill value without a word, or loop
    ("too many links"); refused, what is imported is exactly the bytes that were hashed.
    Hard links stay: they are the file's own structure and its own bytes."""
    import h5py
    try:
        with h5py.File(path, "r") as file:
            problem = file.visititems_links(_link_problem) or file.visititems(_storage_problem)
    except (OSError, RuntimeError, KeyError, ValueError) as error:  # h5py's errors for a damaged file
        raise ValueError(f"{path}: not a readable HDF5 file ({' '.join(str(error).split())})") from None
    if problem:
        raise ValueError(f"{path}: {problem}; an imported file must hold its data itself (hloc and glue-factory "
                         "write neither links nor virtual datasets): write the values into the file")


def _link_problem(name: str, link) -> str | None:
    import h5py
    if isinstance(link, h5py.SoftLink):
        return f"/{name} is a soft link to {link.path}"
    if isinstance(link, h5py.ExternalLink):
        return f"/{name} is an external link to {link.filename}:{link.path}"
    if not isinstance(link, h5py.HardLink):
        return f"/{name} is a user-defined link"
    return None


def _storage_problem(name: str, item) -> str | None:
    import h5py
    if not isinstance(item, h5py.Dataset):
        return None
    if item.is_virtual:
        sources = sorted({source.file_name for source in item.virtual_sources()})
        return f"/{name} is a virtual dataset (its values are read from {', '.join(sources)})"
    if item.id.get_create_plist().get_external_count() > 0:
        return f"/{name} stores its values in external raw files"
    return None


def real_points(values, what: str) -> np.ndarray:
    """N x 2 real numbers as float64: complex numbers (whose imaginary part a cast would drop
    without a word), text, booleans and 0-d or other shapes are refused in one line."""
    array = np.asarray(values)
    if array.dtype.kind not in "fiu":
        raise MatchesError(f"{what}: expected real numbers, got {_kind(array.dtype)}")
    if array.size == 0:
        return np.zeros((0, 2), np.float64)
    if array.ndim != 2 or array.shape[1] != 2:
        raise MatchesError(f"{what} has shape {array.shape}, expected N x 2")
    return array.astype(np.float64)


def index_array(values, what: str, rows: int | None = None) -> np.ndarray:
    """A 1-d array of integer match indices (int64). Floats, text and booleans are refused:
    a float index is a writer's mistake that a cast would hide."""
    array = np.asarray(values)
    if array.dtype.kind not in "iu":
        raise MatchesError(f"{what}: expected integer indices, got {_kind(array.dtype)}")
    if array.ndim != 1 and not (array.ndim == 2 and 1 in array.shape):
        raise MatchesError(f"{what} has shape {array.shape}, expected one index per keypoint")
    array = array.reshape(-1).astype(np.int64)
    if rows is not None and len(array) != rows:
        raise MatchesError(f"{what} has {len(array)} entries for {rows} keypoints")
    return array


def score_array(values, what: str, rows: int) -> np.ndarray:
    array = np.asarray(values)
    if array.dtype.kind not in "fiu":
        raise MatchesError(f"{what}: expected real numbers, got {_kind(array.dtype)}")
    array = array.reshape(-1)
    if len(array) != rows:
        raise MatchesError(f"{what} has {len(array)} entries, expected {rows}")
    return array


def matched(index: np.ndarray, n1: int, what: str) -> np.ndarray:
    """The rows of a matches0-style array that hold a match: -1 is 'no match' (hloc's and
    glue-factory's sentinel); any other negative value, or an index past the second image's
    n1 keypoints, is refused rather than read as 'no match' or wrapped around."""
    bad = (index < -1) | (index >= n1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise MatchesError(f"{what}[{first}] = {int(index[first])}: not -1 (no match) nor an index into the "
                           f"{n1} keypoints of the second image")
    return np.flatnonzero(index >= 0)


def _kind(dtype: np.dtype) -> str:
    return {"c": "complex numbers", "b": "booleans", "S": "bytes", "U": "text", "O": "objects",
            "f": "floats", "V": "records"}.get(dtype.kind, str(dtype))


@dataclass
class ExportItem:
    """One pair on its way out: its names in the dataset, its images' sizes (w, h) and
    intrinsics where the benchmark has them, its matches, and (colmap) the geometry the
    evaluation estimates from them."""

    name: str
    pair: object
    name0: str
    name1: str
    size0: tuple[int, int]
    size1: tuple[int, int]
    matches: Matches
    K0: np.ndarray | None = None
    K1: np.ndarray | None = None
    geometry: dict | None = None
