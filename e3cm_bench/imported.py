"""Matches made elsewhere -> a normal run folder (matches.h5 + config.yaml), evaluated like any run.

Two source formats; keypoints in the stored images' pixels, pixel-centre convention (the
centre of the top-left pixel is (0, 0)), as this toolkit's own:

- ``hloc``: a features file (one group per image, named by its path relative to the
  dataset root, holding ``keypoints`` N x 2; hloc writes them in this convention) and a
  matches file (``matches0``: for each keypoint of the first image, the index of its match
  in the second or -1; optional ``matching_scores0``), pairs keyed the way hloc's
  ``names_to_pair`` keys them (``name0/name1`` with each name's ``/`` turned into ``-``),
  either image first, or hloc's older ``name0_name1``.
- ``npz``: a folder with one ``<pair name>.npz`` per benchmark pair (the names of
  per_pair.csv, e.g. ``v_boat/1-3.npz``), holding ``keypoints0``, ``keypoints1`` (N x 2)
  and optionally ``scores`` (N).

Images are not turned upright: the keypoints are taken as given, in the stored images.
The identity of an imported run is its format and the sha256 of every source file; a run
with other sources in the folder is refused, as a run with other settings is.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import asdict
from pathlib import Path

import h5py
import numpy as np
from rich.console import Console

from .benchmarks import Benchmark, EvalSettings
from .cache import MatchCache
from .datasets.base import Pair, PairList
from .evaluate import CACHE_FILE, CONFIG_FILE, evaluate_and_report
from .files import FolderLock, file_sha256, load_yaml, package_versions, run_environment, save_yaml
from .images import load_image
from .matches import Matches, MatchesError, check_in_image
from .report import print_summary

class MissingPair(LookupError):
    """A benchmark pair the source holds no matches for."""


# --------------------------------------------------------------------------- sources


class HlocSource:
    """hloc's features.h5 + matches.h5 (module docstring)."""

    format = "hloc"
    per_pair = False  # two files for all pairs: any change is another source

    def __init__(self, features: Path, matches: Path) -> None:
        self.features, self.matches = Path(features), Path(matches)
        for path in (self.features, self.matches):
            if not path.is_file():
                raise ValueError(f"{path}: not found")
            if not h5py.is_hdf5(path):
                raise ValueError(f"{path}: not an HDF5 file")

    def files(self, pairs: list[Pair]) -> dict[str, str]:
        return {"features": file_sha256(self.features), "matches": file_sha256(self.matches)}

    def identity(self, files: dict[str, str]) -> dict:
        return {"format": self.format, "files": files}

    def location(self) -> dict:
        return {"features": str(self.features), "matches": str(self.matches)}

    def expected(self, pair: Pair, root: Path) -> str:
        return f"{self.matches}: group {hloc_pair_key(image_name(pair.image0, root), image_name(pair.image1, root))}"

    def read(self, pair: Pair, root: Path) -> Matches:
        name0, name1 = image_name(pair.image0, root), image_name(pair.image1, root)
        with h5py.File(self.features, "r") as features, h5py.File(self.matches, "r") as matches:
            group, swapped = _find_pair(matches, name0, name1)
            if group is None:
                raise MissingPair(f"no pair {hloc_pair_key(name0, name1)} (nor {name1} first) in {self.matches}")
            first, second = (name1, name0) if swapped else (name0, name1)
            points = []
            for name in (first, second):
                if name not in features or "keypoints" not in features[name]:
                    raise MissingPair(f"no keypoints for image {name} in {self.features}")
                points.append(np.asarray(features[name]["keypoints"]))
            if "matches0" not in group:
                raise MatchesError(f"{self.matches}: {group.name} has no matches0")
            index = np.asarray(group["matches0"]).reshape(-1)
            scores = np.asarray(group["matching_scores0"]).reshape(-1) if "matching_scores0" in group else None
        if points[0].ndim != 2 or points[0].shape[-1] != 2 or len(index) != len(points[0]):
            raise MatchesError(f"matches0 has {len(index)} entries for the {len(points[0])} keypoints of {first}")
        if scores is not None and len(scores) != len(index):
            raise MatchesError(f"matching_scores0 has {len(scores)} entries, matches0 {len(index)}")
        valid = np.flatnonzero(index > -1)
        if len(valid) and (index[valid].max() >= len(points[1])):
            raise MatchesError(f"matches0 points past the {len(points[1])} keypoints of {second}")
        k0, k1 = points[0][valid], points[1][index[valid]]
        s = scores[valid] if scores is not None else None
        return Matches(k1, k0, s) if swapped else Matches(k0, k1, s)


def hloc_pair_key(name0: str, name1: str, separator: str = "/") -> str:
    """hloc's names_to_pair: each name's '/' turned into '-', joined by the separator."""
    return separator.join((name0.replace("/", "-"), name1.replace("/", "-")))


def _find_pair(file: h5py.File, name0: str, name1: str) -> tuple[h5py.Group | None, bool]:
    """The pair's group and whether it is stored with name1 first (hloc's find_pair order)."""
    for separator in ("/", "_"):  # "_": hloc's older naming
        for swapped, (a, b) in ((False, (name0, name1)), (True, (name1, name0))):
            key = hloc_pair_key(a, b, separator)
            if key in file and isinstance(file[key], h5py.Group):
                return file[key], swapped
    return None, False


class NpzSource:
    """A folder of <pair name>.npz (module docstring)."""

    format = "npz"
    per_pair = True  # one file per pair: a resume may add or fix the files of pairs not yet imported

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise ValueError(f"{self.folder}: not a folder")

    def path(self, pair_name: str) -> Path:
        return self.folder / f"{pair_name}.npz"

    def files(self, pairs: list[Pair]) -> dict[str, str]:
        """Each pair's file's sha256 (only those of the benchmark's pairs: the folder may hold more)."""
        return {f"{p.name}.npz": file_sha256(self.path(p.name)) for p in pairs if self.path(p.name).is_file()}

    def identity(self, files: dict[str, str]) -> dict:
        """One digest for the folder: each file's hash by name."""
        digest = hashlib.sha256("\n".join(f"{k} {v}" for k, v in sorted(files.items())).encode()).hexdigest()
        return {"format": self.format, "n_files": len(files), "sha256": digest}

    def location(self) -> dict:
        return {"folder": str(self.folder)}

    def expected(self, pair: Pair, root: Path) -> str:
        return str(self.path(pair.name))

    def read(self, pair: Pair, root: Path) -> Matches:
        path = self.path(pair.name)
        if not path.is_file():
            raise MissingPair(f"{path}: not found")
        try:
            with np.load(path, allow_pickle=False) as data:
                missing = [k for k in ("keypoints0", "keypoints1") if k not in data]
                if missing:
                    raise MatchesError(f"{path}: no {', '.join(missing)} (it holds {', '.join(data.files) or 'nothing'})")
                return Matches(data["keypoints0"], data["keypoints1"], data["scores"] if "scores" in data else None)
        except MatchesError as error:
            raise MatchesError(str(error) if str(error).startswith(str(path)) else f"{path}: {error}") from None
        except (OSError, ValueError) as error:
            raise MatchesError(f"{path}: not a readable .npz ({error})") from None


# --------------------------------------------------------------------------- a run


def image_name(path: Path, root: Path) -> str:
    """An image's name in an hloc file: its path relative to the dataset root, with '/'."""
    path = Path(path).resolve()
    try:
        return path.relative_to(root).as_posix()
    except ValueError:
        return path.name


def import_run(
    benchmark: Benchmark, dataset: PairList, root: Path, out: Path, source: HlocSource | NpzSource,
    ev: EvalSettings | None = None, label: str | None = None, skip_bad: bool = False, overwrite: bool = False,
    viz: int = 0, console: Console | None = None,
) -> dict:
    """Write another tool's matches for every benchmark pair into OUT's cache, then evaluate
    them as any run; returns the summary. A pair the source lacks or holds bad matches for
    (wrong shapes, NaN, outside the image) is an error naming it, or with skip_bad is
    skipped and listed in skipped.csv. An interrupted import resumes: pairs already in the
    cache are kept."""
    console = console or Console()
    ev = ev or EvalSettings()
    out = Path(out)
    if viz < 0:
        raise ValueError(f"--viz must be 0 (no drawings) or more, got {viz}")
    root = Path(root).resolve()
    pairs = list(dataset)
    files = source.files(pairs)
    identity = {"imported": source.identity(files)}
    label = label or f"imported-{source.format}"
    with FolderLock(out):
        cache = MatchCache(out / CACHE_FILE)
        config_path = out / CONFIG_FILE
        if overwrite:
            cache.clear()
            for name in (CONFIG_FILE, "per_pair.csv", "summary.csv", "skipped.csv"):
                (out / name).unlink(missing_ok=True)
        done = set(cache.names())
        if config_path.exists():
            _check_resume(load_yaml(config_path), config_path, benchmark, identity, files if source.per_pair else None, done)
        config = {
            "benchmark": benchmark.name, "method": label, "identity": identity,
            "matcher": {"imported": source.format, **source.location()}, "device": None,
            "dataset": {**dataset.describe(), "limit": None, "n_pairs_evaluated": len(pairs)},
            "evaluation": asdict(ev), "versions": package_versions(), "environment": run_environment(),
            "timing": {},
        }
        if source.per_pair:  # each pair's file, so that a resume can tell what changed
            config["imported_files"] = files
        save_yaml(config, config_path)
        skipped = list(dataset.skipped)
        missing: list[str] = []
        t = time.perf_counter()
        for pair in pairs:
            if pair.name in done:
                continue
            try:
                matches = source.read(pair, root)
                size0, size1 = _size(pair.image0), _size(pair.image1)
                check_in_image(matches, size0, size1)
            except MissingPair as error:
                missing.append(pair.name)
                if skip_bad:
                    skipped.append((pair.name, f"not in the source: {error}"))
                continue
            except MatchesError as error:
                if not skip_bad:
                    raise ValueError(f"pair {pair.name}: {error} (the pairs imported before it are kept; "
                                     "--skip-bad skips such pairs)") from None
                skipped.append((pair.name, str(error)))
                continue
            attrs = {"size0": size0, "size1": size1, "match_size0": size0, "match_size1": size1,
                     "match_seconds": float("nan")}
            cache.write(pair.name, matches, attrs)
        if missing and not skip_bad:
            first = next(p for p in pairs if p.name == missing[0])
            raise ValueError(f"{len(missing)} of {len(pairs)} pairs are not in the source (first: {missing[0]}, "
                             f"expected at {source.expected(first, root)}); --skip-bad evaluates the others")
        config["timing"] = {"import_seconds": time.perf_counter() - t}
        pairs_done, summary = evaluate_and_report(benchmark, out, label, pairs, skipped, cache, ev, viz, console)
        config["dataset"]["n_skipped"] = len(skipped)
        save_yaml(config, config_path)
    print_summary(summary, f"{benchmark.name} - {label} ({len(pairs_done)} pairs, imported from {source.format}) -> {out}",
                  console=console)
    return summary


def _check_resume(before: dict, path: Path, benchmark: Benchmark, identity: dict, files: dict | None,
                  done: set[str]) -> None:
    """Refuse to add to matches imported from other sources. files: each pair's file's hash,
    for a source of one file per pair (npz), which may gain or fix the files of pairs not
    imported yet (a resume after a bad pair); those already imported must be the same files."""
    if before.get("benchmark") != benchmark.name:
        raise ValueError(f"{path}: this folder holds a {before.get('benchmark')} run; choose another --out")
    old, new = (before.get("identity") or {}).get("imported") or {}, identity["imported"]
    if files is not None and old.get("format") == new["format"]:
        recorded = before.get("imported_files") or {}
        changed = sorted(n for n in done if recorded.get(f"{n}.npz") != files.get(f"{n}.npz"))
        if not changed:
            return
        why = f"{len(changed)} imported pair file(s) changed since (first: {changed[0]}.npz)"
    elif old == new:
        return
    else:
        why = "the matches in this folder came from elsewhere (imported)"
    raise ValueError(f"{path}: {why}; pass --overwrite to replace them or choose another --out")


_sizes: dict[Path, tuple[int, int]] = {}


def _size(path: Path) -> tuple[int, int]:
    """(w, h) of a stored image (decoded once per path)."""
    path = Path(path)
    if path not in _sizes:
        image = load_image(path)
        _sizes[path] = (int(image.shape[1]), int(image.shape[0]))
    return _sizes[path]
