"""hloc's two files: ``features.h5`` and ``matches.h5`` (hloc c13273b, hloc/utils/io.py,
extract_features.py, match_features.py).

- features: one group per image, named by the image's path relative to the dataset root
  (nested groups where the name holds '/'), holding ``keypoints`` (N x 2, pixel-centre
  convention: extract_features.py rescales with ``(k + .5) * scale - .5``) and, as hloc
  writes it, ``image_size`` (w, h).
- matches: one group per pair, keyed by ``names_to_pair(name0, name1)`` (each name's '/'
  turned into '-', joined by '/'; hloc's older key joins by '_'), holding ``matches0``
  (for each keypoint of the first image the index of its match in the second, -1 for none)
  and ``matching_scores0``. hloc's ``get_matches`` reads both and finds a pair stored with
  the second image first.

Export writes float32 keypoints and float32 scores (hloc writes float16 under its default
``as_half`` and ``matching_scores0`` in float16: exact values would not survive that) and
``matches0`` as int16 (hloc's ``.short()``) while the image's keypoints fit, else int32.
A run's matches are per pair and may be many-to-one, which one keypoint list per image with
``matches0`` cannot hold if keypoints are shared; so each pair's matched keypoints are
appended to its two images' lists (the same location may appear once per pair), which keeps
every match and its order.
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from ..files import file_sha256
from ..matches import Matches, MatchesError
from .base import MissingPair, source_identity, check_declared, check_self_contained, image_name, index_array, matched, real_points, score_array
from .pixels import check_origin, from_origin, to_origin

DEFAULT_ORIGIN = "center"


def hloc_pair_key(name0: str, name1: str, separator: str = "/") -> str:
    """hloc's names_to_pair: each name's '/' turned into '-', joined by the separator."""
    return separator.join((name0.replace("/", "-"), name1.replace("/", "-")))


def find_pair(file: h5py.File, name0: str, name1: str) -> tuple[h5py.Group | None, bool]:
    """The pair's group and whether it is stored with name1 first (hloc's find_pair order)."""
    for separator in ("/", "_"):  # "_": hloc's older naming
        for swapped, (a, b) in ((False, (name0, name1)), (True, (name1, name0))):
            key = hloc_pair_key(a, b, separator)
            if key in file and isinstance(file[key], h5py.Group):
                return file[key], swapped
    return None, False


def read_dataset(item, what: str) -> np.ndarray:
    """An HDF5 dataset's values, its declared size checked before it is read."""
    if not isinstance(item, h5py.Dataset):
        raise MatchesError(f"{what}: not a dataset")
    check_declared(what, item.shape, item.dtype.itemsize)
    return item[()]


class HlocSource:
    """hloc's features.h5 + matches.h5 (module docstring)."""

    format = "hloc"
    per_pair = False  # two files for all pairs: any change is another source

    def __init__(self, features: Path, matches: Path, origin: str | None = None) -> None:
        self.features, self.matches = Path(features), Path(matches)
        self.origin = check_origin(origin or DEFAULT_ORIGIN)
        for path in (self.features, self.matches):
            if not path.is_file():
                raise ValueError(f"{path}: not found")
            if not h5py.is_hdf5(path):
                raise ValueError(f"{path}: not an HDF5 file")
            check_self_contained(path)

    def files(self, pairs) -> dict[str, str]:
        return {"features": file_sha256(self.features), "matches": file_sha256(self.matches)}

    def identity(self, files: dict[str, str]) -> dict:
        return source_identity({"format": self.format, "files": files}, self.origin, DEFAULT_ORIGIN)

    def location(self) -> dict:
        return {"features": str(self.features), "matches": str(self.matches), "pixel_origin": self.origin}

    def expected(self, pair, root: Path) -> str:
        return f"{self.matches}: group {hloc_pair_key(image_name(pair.image0, root), image_name(pair.image1, root))}"

    def read(self, pair, root: Path) -> Matches:
        name0, name1 = image_name(pair.image0, root), image_name(pair.image1, root)
        with h5py.File(self.features, "r") as features, h5py.File(self.matches, "r") as matches:
            group, swapped = find_pair(matches, name0, name1)
            if group is None:
                raise MissingPair(f"no pair {hloc_pair_key(name0, name1)} (nor {name1} first) in {self.matches}")
            first, second = (name1, name0) if swapped else (name0, name1)
            points = []
            for name in (first, second):
                image = features.get(name)
                if not isinstance(image, h5py.Group) or "keypoints" not in image:
                    raise MissingPair(f"no keypoints for image {name} in {self.features}")
                what = f"{self.features}: {name}/keypoints"
                points.append(real_points(read_dataset(image["keypoints"], what), what))
            if "matches0" not in group:
                raise MatchesError(f"{self.matches}: {group.name} has no matches0")
            what = f"{self.matches}: {group.name}/matches0"
            index = index_array(read_dataset(group["matches0"], what), what, rows=len(points[0]))
            scores = None
            if "matching_scores0" in group:
                what_s = f"{self.matches}: {group.name}/matching_scores0"
                scores = score_array(read_dataset(group["matching_scores0"], what_s), what_s, len(index))
        valid = matched(index, len(points[1]), what)
        k0, k1 = from_origin(points[0][valid], self.origin), from_origin(points[1][index[valid]], self.origin)
        s = scores[valid] if scores is not None else None
        return Matches(k1, k0, s) if swapped else Matches(k0, k1, s)


def write_hloc(out: Path, items, origin: str = DEFAULT_ORIGIN) -> list[Path]:
    """features.h5 and matches.h5 in OUT for export.ExportItem's (module docstring)."""
    from ..files import write_atomically

    lists: dict[str, list[np.ndarray]] = {}
    sizes: dict[str, tuple[int, int]] = {}
    offsets = []  # per item: (offset in image 0's list, offset in image 1's list)
    keys: dict[str, str] = {}
    for item in items:
        key = hloc_pair_key(item.name0, item.name1)
        if key in keys or hloc_pair_key(item.name1, item.name0) in keys:
            raise ValueError(f"pairs {keys.get(key) or keys[hloc_pair_key(item.name1, item.name0)]} and {item.name} "
                             f"join the same images ({item.name0}, {item.name1}); hloc keys a pair by its images")
        keys[key] = item.name
        offset = []
        for name, points, size in ((item.name0, item.matches.keypoints0, item.size0),
                                   (item.name1, item.matches.keypoints1, item.size1)):
            listed = lists.setdefault(name, [])
            offset.append(sum(len(p) for p in listed))
            listed.append(to_origin(points, origin).astype(np.float32) if origin != "center" else points)
            sizes[name] = size
        offsets.append(tuple(offset))
    counts = {name: sum(len(p) for p in listed) for name, listed in lists.items()}

    def features(tmp: Path) -> None:
        with h5py.File(tmp, "w") as f:
            for name, listed in lists.items():
                group = f.create_group(name)
                group.create_dataset("keypoints", data=np.concatenate(listed).astype(np.float32).reshape(-1, 2))
                group.create_dataset("image_size", data=np.asarray(sizes[name], np.int64))

    def matches(tmp: Path) -> None:
        with h5py.File(tmp, "w") as f:
            for item, (at0, at1) in zip(items, offsets):
                n = len(item.matches)
                rows = counts[item.name0]
                matches0 = np.full(rows, -1, np.int16 if counts[item.name1] <= np.iinfo(np.int16).max else np.int32)
                scores0 = np.zeros(rows, np.float32)
                matches0[at0:at0 + n] = at1 + np.arange(n)
                scores0[at0:at0 + n] = item.matches.scores
                group = f.create_group(hloc_pair_key(item.name0, item.name1))
                group.create_dataset("matches0", data=matches0)
                group.create_dataset("matching_scores0", data=scores0)

    return [write_atomically(out / "features.h5", features), write_atomically(out / "matches.h5", matches)]
