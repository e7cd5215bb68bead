"""glue-factory's evaluation cache, ``predictions.h5`` (glue-factory main 2d17e3b; the
hydra-config branch, 19c76b7, keys and reads it the same way).

Written by gluefactory/utils/export_predictions.py and read back by
gluefactory/models/cache_loader.py (``CacheLoader``) in eval/hpatches.py and
eval/megadepth1500.py: one group per pair, named by the dataset's ``data["name"]``, holding
``keypoints0``, ``keypoints1`` (each image's keypoints, in the original image's pixels: the
export divides by the resize scales and the loader multiplies them back), ``matches0`` (for
each keypoint of image 0 the index into image 1's, -1 for none), ``matching_scores0``, and
(exported by glue-factory, not needed by its metrics) the ``*1`` and ``keypoint_scores*``
twins. Keypoints are in glue-factory's corner convention: the top-left pixel's centre is
(0.5, 0.5) (gluefactory/geometry/wrappers.py ``from_colmap``; its SuperPoint and DISK wrappers add 0.5).

Pair names: HPatches, ``f"{seq}/{idx}.ppm"`` where idx is the pair's index in glue-factory's
item list (every entry of the dataset folder, sorted, five pairs (1, 2..6) each, the 8 large
sequences left out unless ``ignore_large_images`` is false; datasets/hpatches.py), so that
idx % 5 + 2 is the second image's number whatever the folder holds; MegaDepth-1500, the two
views' names with '/' turned into '-', joined by '/' (gluefactory/datasets/posed_images.py), glue-factory
naming views by file name; any other benchmark, hloc's names_to_pair of the images' paths
relative to the dataset root. Keypoints are written as float64 so that half a pixel added to
our float32 values comes back exactly.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # annotations only: h5py is imported where a file is read
    import h5py

# h5py is imported in the functions that read or write HDF5: the command line imports this module
# for the format registry (registry.py) and answers without loading h5py.

from e3cm_bench.ground.files import file_sha256, write_atomically
from e3cm_bench.ground.matches import Matches, MatchesError
from e3cm_bench.interchange.base import (
    MissingPair,
    source_identity,
    check_self_contained,
    image_name,
    index_array,
    matched,
    real_points,
    score_array,
)
from e3cm_bench.interchange.hloc import hloc_pair_key, read_dataset
from e3cm_bench.interchange.pixels import from_origin, resolve_origin, to_origin
from e3cm_bench.interchange.registry import Format, register



@register
class GluefactoryFormat(Format):
    name = "gluefactory"
    origin = "corner"
    reads = ("PREDICTIONS.h5",)
    import_help = "glue-factory's predictions.h5 (its evaluation cache)."
    writes = "predictions.h5"
    outputs = ("predictions.h5",)
    labelled_by = "predictions"

    def source(self, paths, benchmark: str, origin: str | None = None):
        return GluefactorySource(*paths, benchmark, origin=origin)

    def write(self, out: Path, items: list, origin: str, job) -> list[Path]:
        return write_gluefactory(out, items, origin, benchmark=job.benchmark.name, root=job.root,
                                 ignore_large=bool(job.options.get("exclude_large")))
# glue-factory's HPatches reader leaves these out by default (datasets/hpatches.py ignored_scenes).
LARGE_SEQUENCES = ("i_contruction", "i_crownnight", "i_dc", "i_pencils", "i_whitebuilding", "v_artisans",
                   "v_astronautis", "v_talent")
_HPATCHES_PAIR = re.compile(r"^(?P<seq>[^/]+)/1-(?P<k>[2-6])$")


def hpatches_keys(root: Path, ignore_large: bool) -> dict[tuple[str, int], str]:
    """(sequence, k) -> glue-factory's pair name, numbered as its HPatches reader numbers them."""
    keys, index = {}, 0
    for entry in sorted(p.name for p in Path(root).iterdir()):
        if ignore_large and entry in LARGE_SEQUENCES:
            continue
        for k in range(2, 7):
            keys[(entry, k)] = f"{entry}/{index}.ppm"
            index += 1
    return keys


def pair_key(benchmark: str, pair, root: Path, hpatches: dict | None = None) -> str:
    if benchmark == "hpatches":
        match = _HPATCHES_PAIR.match(pair.name)
        if match is None or hpatches is None or (match["seq"], int(match["k"])) not in hpatches:
            raise ValueError(f"pair {pair.name}: not an HPatches pair (1, k) of a sequence of {root}")
        return hpatches[(match["seq"], int(match["k"]))]
    if benchmark == "megadepth":
        return "/".join(Path(p).name.replace("/", "-") for p in (pair.image0, pair.image1))
    return hloc_pair_key(image_name(pair.image0, root), image_name(pair.image1, root))


def write_gluefactory(out: Path, items, origin: str | None = None, benchmark: str = "", root: Path | None = None,
                      ignore_large: bool = True) -> list[Path]:
    origin = resolve_origin(GluefactoryFormat, origin)
    import h5py
    hpatches = hpatches_keys(root, ignore_large) if benchmark == "hpatches" else None
    keys: dict[str, str] = {}
    for item in items:
        key = pair_key(benchmark, item.pair, root, hpatches)
        if key in keys:
            raise ValueError(f"pairs {keys[key]} and {item.name} both become {key!r} in glue-factory's naming")
        keys[key] = item.name

    def write(tmp: Path) -> None:
        with h5py.File(tmp, "w") as f:
            if hpatches is not None:
                f.attrs["ignore_large_images"] = ignore_large  # glue-factory's data.ignore_large_images to run with
            for key, item in zip(keys, items):
                m, n = item.matches, len(item.matches)
                group = f.create_group(key)
                group.create_dataset("keypoints0", data=to_origin(m.keypoints0, origin))
                group.create_dataset("keypoints1", data=to_origin(m.keypoints1, origin))
                group.create_dataset("matches0", data=np.arange(n, dtype=np.int64))
                group.create_dataset("matches1", data=np.arange(n, dtype=np.int64))
                group.create_dataset("matching_scores0", data=m.scores.astype(np.float32))
                group.create_dataset("matching_scores1", data=m.scores.astype(np.float32))
                group.create_dataset("keypoint_scores0", data=m.scores.astype(np.float32))
                group.create_dataset("keypoint_scores1", data=m.scores.astype(np.float32))

    return [write_atomically(out / "predictions.h5", write)]


class GluefactorySource:
    """glue-factory's predictions.h5 (module docstring)."""

    format = "gluefactory"
    per_pair = False

    def __init__(self, predictions: Path, benchmark: str, origin: str | None = None) -> None:
        import h5py
        self.predictions = Path(predictions)
        self.benchmark = benchmark
        self.origin = resolve_origin(GluefactoryFormat, origin)
        if not self.predictions.is_file():
            raise ValueError(f"{self.predictions}: not found")
        if not h5py.is_hdf5(self.predictions):
            raise ValueError(f"{self.predictions}: not an HDF5 file")
        check_self_contained(self.predictions)
        self._hpatches: dict[tuple[str, int], str] | None = None

    def files(self, pairs) -> dict[str, str]:
        return {"predictions": file_sha256(self.predictions)}

    def identity(self, files: dict[str, str]) -> dict:
        return source_identity({"format": self.format, "files": files}, self.origin, GluefactoryFormat.origin)

    def location(self) -> dict:
        return {"predictions": str(self.predictions), "pixel_origin": self.origin}

    def _hpatches_keys(self, file: h5py.File) -> dict[tuple[str, int], str]:
        """(sequence, k) -> the file's pair name: glue-factory's index is 5 per sequence in
        order, so idx % 5 + 2 is k without knowing which folder glue-factory listed."""
        import h5py
        if self._hpatches is None:
            self._hpatches, base = {}, {}
            for seq, group in file.items():
                if not isinstance(group, h5py.Group):
                    continue
                for name in group:
                    found = re.fullmatch(r"(\d+)\.ppm", name)
                    if found is None:
                        continue
                    index = int(found[1])
                    if base.setdefault(seq, index // 5) != index // 5:
                        raise ValueError(f"{self.predictions}: sequence {seq} has pairs {seq}/{name} and others "
                                         "more than 5 apart; not glue-factory's HPatches numbering")
                    self._hpatches[(seq, index % 5 + 2)] = f"{seq}/{name}"
        return self._hpatches

    def _key(self, file: h5py.File, pair, root: Path) -> tuple[str, bool]:
        if self.benchmark == "hpatches":
            match = _HPATCHES_PAIR.match(pair.name)
            key = self._hpatches_keys(file).get((match["seq"], int(match["k"]))) if match else None
            return key or f"{pair.name.split('/')[0]}/<index>.ppm", False
        key = pair_key(self.benchmark, pair, root)
        first, second = key.split("/", 1) if key.count("/") == 1 else (None, None)
        if key not in file and first is not None and f"{second}/{first}" in file:
            return f"{second}/{first}", True
        return key, False

    def expected(self, pair, root: Path) -> str:
        import h5py
        with h5py.File(self.predictions, "r") as file:
            return f"{self.predictions}: group {self._key(file, pair, root)[0]}"

    def read(self, pair, root: Path) -> Matches:
        import h5py
        with h5py.File(self.predictions, "r") as file:
            key, swapped = self._key(file, pair, root)
            group = file.get(key)
            if not isinstance(group, h5py.Group) or "keypoints0" not in group:
                raise MissingPair(f"no pair {key} in {self.predictions}")
            where = f"{self.predictions}: {key}"
            for name in ("keypoints1", "matches0"):
                if name not in group:
                    raise MatchesError(f"{where} has no {name}")
            points = [
                real_points(read_dataset(group[k], f"{where}/{k}"), f"{where}/{k}")
                for k in ("keypoints0", "keypoints1")
            ]
            index = index_array(
                read_dataset(group["matches0"], f"{where}/matches0"), f"{where}/matches0", len(points[0])
            )
            scores = None
            if "matching_scores0" in group:
                scores = score_array(read_dataset(group["matching_scores0"], f"{where}/matching_scores0"),
                                     f"{where}/matching_scores0", len(index))
        valid = matched(index, len(points[1]), f"{where}/matches0")
        k0, k1 = from_origin(points[0][valid], self.origin), from_origin(points[1][index[valid]], self.origin)
        s = scores[valid] if scores is not None else None
        return Matches(k1, k0, s) if swapped else Matches(k0, k1, s)
