"""One's own images, no ground truth: a folder of images -> the pairs to match -> the match stage
every benchmark runs (cache, resume, feature reuse: runner.run_benchmark) -> a reconstruction
with unknown intrinsics (sfm/uncalibrated.py). What `e3cm-bench reconstruct` runs.

`ImageFolder` is the pairs: every image file under the folder (sub-folders included, hidden ones
not), named by its path relative to it, in name order; the graph is every pair (exhaustive, as
hloc's pairs_from_exhaustive), each image with the next K (``window``: a video or a walk), or a
file of ``name0 name1`` lines (``pairs``: from retrieval, or by hand). `RECONSTRUCT` is the
"benchmark" that scores them: it has no ground truth, so it scores nothing; its per-pair rows
say how many matches COLMAP's verification kept and where each image went, and its summary is
the reconstruction's numbers and its cost (matching and mapping). It is not in the benchmark
registry (it is no benchmark: no paper table, no ground truth, no command of its own), but the
registry finds it by name (benchmarks.UNLISTED): `table` lists its runs and `report` builds their
page; `compare` says in one line that they hold no per-pair score.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import time

import numpy as np
import pandas as pd

from e3cm_bench.benchmarks.base import DUPLICATES, Benchmark, with_duplicates
from e3cm_bench.benchmarks.eval_settings import EvalSettings
from e3cm_bench.datasets.base import DatasetError, Pair, PairList, require_directory
from e3cm_bench.ground.files import write_csv
from e3cm_bench.ground.matches import Matches, distinct
from e3cm_bench.sfm import views as V
from e3cm_bench.sfm.dataset import DEFAULT_MAX_PAIRS, _count, _window, check_graph_size, graph_components
from e3cm_bench.sfm.protocol import BY_COLMAP, ReconstructionProtocol, keypoints_are_detections, protocol_of
from e3cm_bench.sfm.uncalibrated import reconstruct_images, settings as mapper_settings

# Under this share of the images in its largest model, a run says its models fragment (one line):
# the 20 KITTI frames with xfeat gave 9 registered in 4 models, the largest of 3 (issue 80).
FRAGMENTED = 0.8
DEFAULT_MAPPER = "global"
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".ppm", ".pgm", ".bmp", ".tif", ".tiff", ".webp")
CAMERA_MODELS = ("SIMPLE_RADIAL", "PINHOLE")


def image_names(root: Path) -> list[str]:
    """The image files under root (hidden folders and files left out), as sorted relative paths."""
    names = []
    for path in root.rglob("*"):
        relative = path.relative_to(root)
        if (
            path.suffix.lower() in IMAGE_SUFFIXES
            and path.is_file()
            and not any(p.startswith(".") for p in relative.parts)
        ):
            names.append(relative.as_posix())
    return sorted(names)


@dataclass(frozen=True)
class FolderOptions:
    """How a folder of images becomes pairs and a reconstruction (reconstruct's flags)."""

    window: str | int | None = None
    pairs: str | Path | None = None
    camera_model: str = "SIMPLE_RADIAL"
    camera_per_image: bool = False
    max_pairs: str | int | None = None
    allow_disconnected: bool = False


@dataclass(frozen=True)
class FolderSetup:
    """Where a folder's images lie and how their cameras are modelled, the same object on every pair
    (views.ViewPair.setup). The protocol (COLMAP's verification, sfm's preset; the mapper, its seeds,
    the merge radius) is the evaluation's: RECONSTRUCT's eval_defaults under the user's options."""

    root: Path
    camera_model: str = "SIMPLE_RADIAL"
    camera_per_image: bool = False


class ImageFolder(PairList):
    """The pairs of a folder of images: exhaustive, ``window`` K, or the ``pairs`` file's."""

    name = "images"

    def __init__(self, root: str | Path, skip_bad: bool = False, **options) -> None:
        """options: FolderOptions' fields (window, pairs, camera_model, camera_per_image, max_pairs,
        allow_disconnected), as the command's flags give them."""
        if "single_camera" in options:  # records written before the option took its flag's name
            options["camera_per_image"] = not options.pop("single_camera")
        o = FolderOptions(**options)
        window, pairs, camera_model = o.window, o.pairs, o.camera_model
        camera_per_image, max_pairs, allow_disconnected = o.camera_per_image, o.max_pairs, o.allow_disconnected
        self.root = require_directory(root, "image")
        self.window = _window(window)
        self.pairs_file = Path(pairs) if pairs is not None else None
        if self.window is not None and self.pairs_file is not None:
            raise DatasetError(f"{self.pairs_file}: --window and --pairs are two pair graphs; give one")
        if camera_model not in CAMERA_MODELS:
            raise DatasetError(f"--camera-model must be one of {', '.join(CAMERA_MODELS)}, got {camera_model!r}")
        self.camera_model, self.camera_per_image = camera_model, bool(camera_per_image)
        self.views = [V.View(name, self.root / name, None) for name in image_names(self.root)]
        if len(self.views) < V.MIN_VIEWS:
            raise DatasetError(f"{self.root}: holds {len(self.views)} image(s) ({', '.join(IMAGE_SUFFIXES)}); "
                               f"a reconstruction needs at least {V.MIN_VIEWS}")
        self.max_pairs = _count(max_pairs, "--max-pairs") or DEFAULT_MAX_PAIRS
        self.allow_disconnected = bool(allow_disconnected)
        if self.pairs_file is not None:
            listed = V.read_graph(self.pairs_file, self.views)
        elif self.window is not None:
            listed = V.window(self.views, self.window)
        else:
            listed = V.exhaustive(self.views)
        # counted before one pair is built (a generator above): 3000 images are 4.5 million pairs
        count = len(listed) if isinstance(listed, list) else V.graph_size(len(self.views), self.window)
        check_graph_size(self.pairs_file or self.root, len(self.views), count, count, self.max_pairs,
                         self.pairs_file is None and self.window is None, "--window K, --pairs FILE")
        setup = self.reconstruction()
        built = [V.ViewPair(name=f"{item.view0}--{item.view1}", image0=self.root / item.view0,
                            image1=self.root / item.view1, view0=item.view0, view1=item.view1, setup=setup)
                 for item in listed]
        super().__init__(built, self.pairs_file or self.root, skip_bad)
        self.components = graph_components(
            self.pairs, self.views, self.allow_disconnected, self.pairs_file or self.root
        )

    def preamble(self) -> str:
        sizes = [len(names) for names in self.components]
        if len(sizes) == 1:
            return f"pair graph: one component of {sizes[0]} images"
        return f"pair graph: {len(sizes)} components of {', '.join(map(str, sizes))} images (--allow-disconnected)"

    def reconstruction(self) -> FolderSetup:
        """Where the images lie and how their cameras are modelled: it travels with each pair
        (ViewPair.setup) to the evaluation that maps them."""
        return FolderSetup(self.root, self.camera_model, self.camera_per_image)

    def settings(self) -> dict:
        graph = (f"file {self.pairs_file}" if self.pairs_file is not None
                 else f"window {self.window}" if self.window is not None else "exhaustive")
        return {"dataset": self.name, "root": str(self.root), "pair_graph": graph, "window": self.window,
                "pairs": str(self.pairs_file) if self.pairs_file is not None else None, "n_images": len(self.views),
                "max_pairs": self.max_pairs, "allow_disconnected": self.allow_disconnected,
                "reconstruction": mapper_settings(self.camera_model, self.camera_per_image)}


def model_facts(found) -> dict:
    """A reconstruction's numbers with its largest model's (sparse/0, the model a user opens
    first): several models may share images, and their points then count the same scene twice
    (136 + 97 = 233 in one run), so the model's own points are said beside the sum over models."""
    largest = found.models[0] if found.models else None
    return {**found.numbers(), "largest_model_images": len(largest.poses) if largest else 0,
            "largest_model_points": largest.points if largest else 0}


def run_cost(matches: Sequence[Matches], mapping_seconds: float, n_images: int) -> dict:
    """The cost of the whole run, not only its matching (evaluate_stage's seconds_per_pair):
    COLMAP's verification, calibration and mapper (every seed's) in seconds, and the matching and
    the mapping together per image. Measurements: in summary.csv, never in per_pair.csv (cost
    columns: pipeline/evaluate.COST_KEYS)."""
    matched = float(np.nansum([float(m.info.get("match_seconds", np.nan)) for m in matches]))
    return {"mapping_seconds": mapping_seconds,
            "seconds_per_image": (matched + mapping_seconds) / n_images if n_images else float("nan")}


def fragments(summary: Mapping) -> str | None:
    """One line where the models fragment: the largest holds under FRAGMENTED of the images
    (None otherwise)."""
    n, largest = int(summary.get("n_images", 0)), int(summary.get("largest_model_images", 0))
    if not n or largest >= FRAGMENTED * n:
        return None
    share = largest / n
    return (f"the models fragment: the largest holds {largest} of {n} images ({share:.0%}), "
            f"{int(summary.get('n_models', 0))} model(s) in all; the matches of this folder do not join its "
            f"images into one scene (try --mapper, a wider --window, or another matcher)")


@dataclass(frozen=True)
class ReconstructBenchmark(Benchmark):
    """A folder of images reconstructed from a matcher's matches: no ground truth, so no score;
    the rows and the summary say what the reconstruction holds."""

    table_extras: tuple[str, ...] = ("n_pairs", "registered_images", "largest_model_images", "largest_model_points",
                                     "n_images", "n_models", "points", "mean_track_length", "mean_reprojection_error")
    evaluates_set = True
    default_interval_seeds: int = 1  # no score, no interval

    def pair_columns(self, ev: EvalSettings) -> list[str]:
        return with_duplicates(["pair", "n_matches", "n_verified", "registered0", "registered1", "model"])

    def evaluate_pair(self, pair: Pair, matches: Matches, ev: EvalSettings) -> dict:
        raise ValueError("reconstruct maps the pairs of a folder together (evaluate_set), not one at a time")

    def evaluate_set(self, pairs: Sequence[Pair], matches: Sequence[Matches], ev: EvalSettings,
                     workdir: Path | None, matcher: str | None = None) -> tuple[list[dict], dict]:
        if workdir is None:
            raise ValueError("reconstruct writes its model into the run folder: give one")
        kept = [distinct(m) for m in matches]
        how = pairs[0].setup
        if not isinstance(how, FolderSetup):
            raise ValueError("reconstruct maps an ImageFolder's pairs (views.ViewPair with a FolderSetup)")
        protocol = protocol_of(ev).resolved(keypoints_are_detections(matcher))
        started = time.perf_counter()
        seeds, verified, calibrated = reconstruct_images(
            pairs, [k for k, _ in kept], workdir, how.root, seed=ev.seed, protocol=protocol,
            camera_model=how.camera_model, camera_per_image=how.camera_per_image)
        mapping_seconds = time.perf_counter() - started
        found = seeds[0]  # the model in OUT/sparse: the first seed's; the others' under seed-K/
        rows = []
        for pair, (k, repeats), n_verified in zip(pairs, kept, verified):
            (placed0, placed1) = found.placed(pair.view0, pair.view1)
            same = placed0 is not None and placed1 is not None and placed0[0] == placed1[0]
            rows.append({"pair": pair.name, "n_matches": len(k), "n_verified": n_verified,
                         "registered0": int(placed0 is not None), "registered1": int(placed1 is not None),
                         "model": placed0[0] if same else -1, DUPLICATES: repeats})
        if len(seeds) > 1:
            write_csv(pd.DataFrame([{"seed": ev.seed + s, "focals_calibrated": int(c), **model_facts(r)}
                                    for s, (r, c) in enumerate(zip(seeds, calibrated))]),
                      workdir / "per_seed.csv")
        return rows, {**model_facts(found), "merge_px": protocol.merge_px, "mapper": protocol.mapper,
                      "mapper_seeds": protocol.mapper_seeds, "focals_calibrated": int(calibrated[0]),
                      **run_cost(matches, mapping_seconds, len(found.images))}

    def summarize(self, rows: Sequence[Mapping], ev: EvalSettings) -> dict:
        rows = list(rows)
        mean = lambda key: float(np.mean([float(r[key]) for r in rows])) if rows else 0.0  # noqa: E731
        return {"n_pairs": len(rows), "n_matches": mean("n_matches"), "n_verified": mean("n_verified")}

    def required_summary_columns(self) -> list[str]:
        return ["n_pairs", "n_matches", "registered_images", "n_models"]

    def correct_mask(self, pair: Pair, matches: Matches, ev: EvalSettings) -> None:
        return None  # no ground truth to call a match correct: drawings colour matches by height alone

    def plot_run(self, label: str, summary: dict, per_pair: pd.DataFrame, out: Path) -> None:
        return None  # its picture is the model: open OUT/sparse/0 in COLMAP's GUI

    def plot_comparison(self, runs, stem: Path) -> list[Path]:
        return []


RECONSTRUCT = ReconstructBenchmark(
    name="reconstruct",
    dataset=ImageFolder,
    dataset_options=(
        "window",
        "pairs",
        "camera_model",
        "camera_per_image",
        "max_pairs",
        "allow_disconnected",
    ),
    summary="A folder of images (no ground truth) -> pairs -> matches -> a COLMAP model with unknown intrinsics.",
    default_max_side=1200,
    # sfm's protocol, a folder's own defaults: COLMAP's verification, one seed (one model to open)
    eval_defaults=ReconstructionProtocol(mapper=DEFAULT_MAPPER, mapper_seeds=1, verification=BY_COLMAP).record(),
)
