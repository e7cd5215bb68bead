"""Matches made elsewhere -> a normal run folder (matches.h5 + config.yaml), evaluated like any run.

The sources (e3cm_bench.interchange: hloc's two files, a folder of npz, a COLMAP database,
glue-factory's predictions.h5) turn each benchmark pair into Matches in the stored images'
pixels, pixel-centre convention (the centre of the top-left pixel is (0, 0)), as this
toolkit's own, converting from each format's convention (docs/interchange.md).

Images are not turned upright: the keypoints are taken as given, in the stored images.
The identity of an imported run is its format and the sha256 of every source file (and the
pixel origin where it is not the format's own); a run with other sources in the folder is
refused, as a run with other settings is. On a benchmark with homographies the imported
matches are checked for the other pixel convention (interchange.pixels.half_pixel_check): a
warning when half a pixel fits the ground truth clearly better.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

from rich.console import Console

from e3cm_bench.storage.cache import MatchCache
from e3cm_bench.datasets.base import Pair
from e3cm_bench.ground.images import load_image
from e3cm_bench.interchange import ColmapSource, GluefactorySource, HlocSource, MissingPair, NpzSource, half_pixel_check
from e3cm_bench.interchange.base import image_name
from e3cm_bench.interchange.hloc import hloc_pair_key
from e3cm_bench.ground.matches import MatchesError, check_in_image
from e3cm_bench.interchange.registry import source_label
from e3cm_bench.storage import RunConfig, RunFolder
from e3cm_bench.pipeline.driver import PairRun, run_pipeline
from e3cm_bench.pipeline.request import RunRequest

# The sources live in e3cm_bench.interchange (its registry: registry.formats()); these names stay importable from here.
__all__ = ["ColmapSource", "GluefactorySource", "HlocSource", "MissingPair", "NpzSource", "hloc_pair_key",
           "image_name", "import_run"]


def import_run(request: RunRequest, source, label: str | None = None, console: Console | None = None) -> dict:
    """Write another tool's matches for every pair of the request's dataset (request.dataset,
    request.root: the images' folder) into request.out's cache, then evaluate them as any run;
    returns the summary. A pair the source lacks or holds bad matches for (wrong shapes, NaN,
    outside the image) is an error naming it, or with request.skip_bad is skipped and listed in
    skipped.csv. An interrupted import resumes: pairs already in the cache are kept.
    request.limit: only the first N pairs of the dataset (as a benchmark run's --limit).
    request.dataset_load: how to load the pairs again (RunConfig.dataset_load_of), so that the
    run can be exported or its matches drawn later."""
    console = console or Console()
    run = ImportRun.of(request, source, label)
    summary, = run_pipeline([run], console)
    return summary


@dataclass
class ImportRun(PairRun):
    """The import hook: the matches read from another tool's files (a format's source)."""

    request: RunRequest = None
    source: object = None
    label: str = ""
    done: set = field(default_factory=set)

    @classmethod
    def of(cls, request: RunRequest, source, label: str | None) -> ImportRun:
        return cls(request.bench, RunFolder(request.out), request.ev, request.viz, request.overwrite, request=request,
                   source=source, label=label or source_label(source))

    def open(self, console: Console) -> None:
        """The sources' identity against what the folder holds, and the record."""
        request, source, folder = self.request, self.source, self.folder
        limit, dataset = request.limit, request.dataset
        self.pairs = list(dataset)[:limit] if limit else list(dataset)
        files = source.files(self.pairs)
        identity = {"imported": source.identity(files)}
        self.cache, todo = folder.resume(self.pairs)
        self.done = {p.name for p in self.pairs} - {p.name for p in todo}
        previous = folder.run_config(required=False)
        if previous is not None and self.done:
            folder.check_imported(
                previous, self.benchmark.name, identity, files if source.per_pair else None, self.done
            )
        elif previous is not None and previous.identity != identity:  # nothing imported: nothing to mix with
            console.print(f"{request.out}: holds no matches of its earlier sources; importing these", markup=False,
                          highlight=False, soft_wrap=True)
        self.config = RunConfig(
            benchmark=self.benchmark.name, method=self.label, identity=identity,
            matcher={"imported": source.format, **source.location()}, device=None,
            dataset={**dataset.describe(), "limit": limit, "n_pairs_evaluated": len(self.pairs)},
            evaluation=self.ev.record(), environment=RunConfig.environment_now(), dataset_load=request.dataset_load,
            # each pair's file, so that a resume can tell what changed
            imported_files=files if source.per_pair else None,
        )
        self.skipped = list(dataset.skipped)

    @classmethod
    def produce(cls, runs: list[ImportRun], console: Console) -> None:
        for run in runs:
            root = Path(run.request.root).resolve()
            run.config.timing = _import_all(run.source, run.pairs, run.done, root, run.cache, run.request.skip_bad,
                                            run.skipped)
            run.config.pixel_origin_check = _convention_check(run.pairs, run.cache, run.source, console)

    def title(self, summary: dict) -> str:
        return (f"{self.benchmark.name} - {self.label} ({self.evaluated} pairs, imported from {self.source.format}) "
                f"-> {self.request.out}")


def _import_all(source, pairs: list[Pair], done: set[str], root: Path, cache: MatchCache, skip_bad: bool,
                skipped: list) -> dict:
    """The produce-matches hook of an import: every pair not `done` read from the source into
    the cache; returns the timing block."""
    missing: list[str] = []
    t = time.perf_counter()
    try:
        _import_pairs(source, pairs, done, root, cache, skip_bad, skipped, missing)
    finally:
        getattr(source, "close", lambda: None)()
    if missing and not skip_bad:
        first = next(p for p in pairs if p.name == missing[0])
        raise ValueError(f"{len(missing)} of {len(pairs)} pairs are not in the source (first: {missing[0]}, "
                         f"expected at {source.expected(first, root)}); --skip-bad evaluates the others")
    return {"import_seconds": time.perf_counter() - t}


def _import_pairs(source, pairs: list[Pair], done: set[str], root: Path, cache: MatchCache, skip_bad: bool,
                  skipped: list, missing: list[str]) -> None:
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


def _convention_check(pairs: list[Pair], cache: MatchCache, source, console: Console) -> dict | None:
    """interchange.pixels.half_pixel_check on the imported pairs that carry a homography: a
    warning when half a pixel on both images fits clearly better (the file's maker used the
    other convention, or --pixel-origin says the wrong one); its figures for config.yaml."""
    names = set(cache.names())
    check = half_pixel_check((pair, cache.read(pair.name)) for pair in pairs
                             if getattr(pair, "H", None) is not None and pair.name in names)
    if check is None:
        return None
    if check.other_fits_better:
        other = "corner" if getattr(source, "origin", "center") == "center" else "center"
        console.print(f"warning: {check.line()}: the file looks written in the other pixel convention; "
                      f"import it again with --pixel-origin {other} --overwrite", markup=False, highlight=False,
                      soft_wrap=True)
    return {"mma@1": check.as_read, "mma@1_shifted": check.shifted, "shift_px": check.shift, "z": check.z,
            "n_matches": check.n_matches, "other_fits_better": check.other_fits_better}


_sizes: dict[Path, tuple[int, int]] = {}


def _size(path: Path) -> tuple[int, int]:
    """(w, h) of a stored image (decoded once per path)."""
    path = Path(path)
    if path not in _sizes:
        image = load_image(path)
        _sizes[path] = (int(image.shape[1]), int(image.shape[0]))
    return _sizes[path]
