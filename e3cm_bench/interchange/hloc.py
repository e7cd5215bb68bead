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
``matches0`` as int16 (hloc's ``.short()``) while the second image's keypoints fit, else int32.

One keypoint list per image, as hloc's own extractors give: a location that several pairs
matched is listed once (tracks.merge_keypoints: exact repeats, or within ``--merge-px``), so
that hloc's triangulation and reconstruction chain the pairs into tracks. ``matches0`` holds
one match per keypoint of the first image, while a run's matches may be many-to-one (SIFT
lists one location once per orientation; a radius merges near points): where a pair matches
one keypoint of its first image twice, the later match gets a keypoint of its own, appended
to that image's list at the match's coordinates, so that no match is lost.

hloc's readers return a pair's matches in the order of the first image's keypoints, which is
not the run's order once keypoints are shared; each pair's group therefore also holds
``e3cm_order`` (ORDER_KEY): the first image's keypoint index of each match in the run's order.
hloc reads only the datasets it names and ignores it; import reads the matches in that order
where it is present, so that a round trip gives the run's per_pair.csv byte for byte.

``pairs.txt`` beside them lists the pairs, ``name0 name1`` a line in the run's order: the
pairs file hloc's match_features, triangulation and reconstruction take.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # annotations only: h5py is imported where a file is read
    import h5py

# h5py is imported in the functions that read or write HDF5: the command line imports this module
# for the format registry (registry.py) and answers without loading h5py.

from e3cm_bench.ground.files import file_sha256
from e3cm_bench.ground.matches import Matches, MatchesError
from e3cm_bench.interchange.base import (
    MissingPair,
    source_identity,
    check_declared,
    check_self_contained,
    image_name,
    index_array,
    matched,
    real_points,
    score_array,
)
from e3cm_bench.interchange.pixels import from_origin, resolve_origin, to_origin
from e3cm_bench.interchange.registry import Format, register


@register
class HlocFormat(Format):
    name = "hloc"
    origin = "center"
    reads = ("FEATURES.h5", "MATCHES.h5")
    import_help = "FEATURES.h5 MATCHES.h5 written by hloc (or in its layout)."
    writes = "features.h5, matches.h5, pairs.txt"
    outputs = ("features.h5", "matches.h5", "pairs.txt")
    merges = True
    labelled_by = "matches"

    def source(self, paths, benchmark: str, origin: str | None = None):
        return HlocSource(*paths, origin=origin)

    def write(self, out: Path, items: list, origin: str, job) -> list[Path]:
        job.layout = hloc_layout(items, job.merged)  # export reports the keypoints it appends
        return write_hloc(out, items, origin, job.merge_px, layout=job.layout)

    def label_stem(self, path: Path) -> str:
        return path.stem.removeprefix("matches-")  # hloc's own naming: matches-<method>.h5

# A pair group's dataset of our own (module docstring): the run's order of its matches.
ORDER_KEY = "e3cm_order"


def hloc_pair_key(name0: str, name1: str, separator: str = "/") -> str:
    """hloc's names_to_pair: each name's '/' turned into '-', joined by the separator."""
    return separator.join((name0.replace("/", "-"), name1.replace("/", "-")))


def find_pair(file: h5py.File, name0: str, name1: str) -> tuple[h5py.Group | None, bool]:
    """The pair's group and whether it is stored with name1 first (hloc's find_pair order)."""
    import h5py
    for separator in ("/", "_"):  # "_": hloc's older naming
        for swapped, (a, b) in ((False, (name0, name1)), (True, (name1, name0))):
            key = hloc_pair_key(a, b, separator)
            if key in file and isinstance(file[key], h5py.Group):
                return file[key], swapped
    return None, False


def read_dataset(item, what: str) -> np.ndarray:
    """An HDF5 dataset's values, its declared size checked before it is read."""
    import h5py
    if not isinstance(item, h5py.Dataset):
        raise MatchesError(f"{what}: not a dataset")
    check_declared(what, item.shape, item.dtype.itemsize)
    return item[()]


class HlocSource:
    """hloc's features.h5 + matches.h5 (module docstring)."""

    format = "hloc"
    per_pair = False  # two files for all pairs: any change is another source

    def __init__(self, features: Path, matches: Path, origin: str | None = None) -> None:
        import h5py
        self.features, self.matches = Path(features), Path(matches)
        self.origin = resolve_origin(HlocFormat, origin)
        for path in (self.features, self.matches):
            if not path.is_file():
                raise ValueError(f"{path}: not found")
            if not h5py.is_hdf5(path):
                raise ValueError(f"{path}: not an HDF5 file")
            check_self_contained(path)

    def files(self, pairs) -> dict[str, str]:
        return {"features": file_sha256(self.features), "matches": file_sha256(self.matches)}

    def identity(self, files: dict[str, str]) -> dict:
        return source_identity({"format": self.format, "files": files}, self.origin, HlocFormat.origin)

    def location(self) -> dict:
        return {"features": str(self.features), "matches": str(self.matches), "pixel_origin": self.origin}

    def expected(self, pair, root: Path) -> str:
        return f"{self.matches}: group {hloc_pair_key(image_name(pair.image0, root), image_name(pair.image1, root))}"

    def read(self, pair, root: Path) -> Matches:
        import h5py
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
            what_o = f"{self.matches}: {group.name}/{ORDER_KEY}"
            order = read_dataset(group[ORDER_KEY], what_o) if ORDER_KEY in group else None
        valid = matched(index, len(points[1]), what)
        if order is not None:
            valid = run_order(order, valid, what_o)
        k0, k1 = from_origin(points[0][valid], self.origin), from_origin(points[1][index[valid]], self.origin)
        s = scores[valid] if scores is not None else None
        return Matches(k1, k0, s) if swapped else Matches(k0, k1, s)


def run_order(values: np.ndarray, valid: np.ndarray, what: str) -> np.ndarray:
    """The matched rows of matches0 in the run's order, as a pair's ORDER_KEY lists them: each
    matched row exactly once, else the file is refused."""
    order = index_array(values, what)
    if len(order) != len(valid) or not np.array_equal(np.sort(order), valid):
        raise MatchesError(f"{what}: not the {len(valid)} matched keypoints of matches0, each once")
    return order


def hloc_layout(items, merged) -> tuple[dict[str, np.ndarray], list[tuple[np.ndarray, np.ndarray]]]:
    """(per image its keypoints, per pair the (first, second) image's keypoint index of each
    match in the run's order) from tracks.merge_keypoints' result, with a keypoint appended for
    each later match of a first-image keypoint that the pair already matched (module docstring)."""
    keypoints, indices = merged
    lists = {name: [points] for name, points in keypoints.items()}
    counts = {name: len(points) for name, points in keypoints.items()}
    pairs = []
    for item, index in zip(items, indices):
        first = index[:, 0].copy()
        repeat = np.ones(len(first), bool)
        repeat[np.unique(first, return_index=True)[1]] = False  # a keypoint's first match keeps it
        if repeat.any():
            n = int(repeat.sum())
            first[repeat] = counts[item.name0] + np.arange(n)
            lists[item.name0].append(np.asarray(item.matches.keypoints0, np.float64).reshape(-1, 2)[repeat])
            counts[item.name0] += n
        pairs.append((first, index[:, 1]))
    return {name: np.concatenate(listed) for name, listed in lists.items()}, pairs


def write_hloc(out: Path, items, origin: str | None = None, merge_px: float = 0.0, layout=None) -> list[Path]:
    """features.h5, matches.h5 and pairs.txt in OUT for base.ExportItem's (module docstring).
    layout: hloc_layout's result where the caller has it, else made here with merge_px."""
    origin = resolve_origin(HlocFormat, origin)
    import h5py
    from e3cm_bench.ground.files import write_atomically
    from e3cm_bench.interchange.tracks import merge_keypoints

    keys: dict[str, str] = {}
    for item in items:
        key = hloc_pair_key(item.name0, item.name1)
        if key in keys or hloc_pair_key(item.name1, item.name0) in keys:
            raise ValueError(f"pairs {keys.get(key) or keys[hloc_pair_key(item.name1, item.name0)]} and {item.name} "
                             f"join the same images ({item.name0}, {item.name1}); hloc keys a pair by its images")
        keys[key] = item.name
        spaced = next((n for n in (item.name0, item.name1) if len(n.split()) != 1 or n != n.strip()), None)
        if spaced is not None:
            raise ValueError(f"image name {spaced!r} holds white space, which hloc's pairs file cannot hold")
    if layout is None:
        layout = hloc_layout(items, merge_keypoints(
            ((item.name0, item.name1, item.matches.keypoints0, item.matches.keypoints1) for item in items), merge_px))
    keypoints, pairs = layout
    sizes = {name: size for item in items for name, size in ((item.name0, item.size0), (item.name1, item.size1))}

    def features(tmp: Path) -> None:
        with h5py.File(tmp, "w") as f:
            for name, points in keypoints.items():
                group = f.create_group(name)
                group.create_dataset("keypoints", data=to_origin(points, origin).astype(np.float32).reshape(-1, 2))
                group.create_dataset("image_size", data=np.asarray(sizes[name], np.int64))

    def matches(tmp: Path) -> None:
        with h5py.File(tmp, "w") as f:
            for item, (first, second) in zip(items, pairs):
                rows, columns = len(keypoints[item.name0]), len(keypoints[item.name1])
                matches0 = np.full(rows, -1, np.int16 if columns <= np.iinfo(np.int16).max else np.int32)
                scores0 = np.zeros(rows, np.float32)
                matches0[first] = second
                scores0[first] = item.matches.scores
                group = f.create_group(hloc_pair_key(item.name0, item.name1))
                group.create_dataset("matches0", data=matches0)
                group.create_dataset("matching_scores0", data=scores0)
                group.create_dataset(ORDER_KEY, data=first.astype(np.int64))

    def pair_list(tmp: Path) -> None:
        tmp.write_text("".join(f"{item.name0} {item.name1}\n" for item in items))

    return [write_atomically(out / "features.h5", features), write_atomically(out / "matches.h5", matches),
            write_atomically(out / "pairs.txt", pair_list)]
