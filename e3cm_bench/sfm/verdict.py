"""Finished runs of several matchers over one set of images read back for the ground-truth-free
verdict (sfm/consensus.py): each run's pairs and, per pair, the relative pose its own
reconstruction gives. A `reconstruct` run keeps its models in OUT/sparse/N, an sfm run in
OUT/sfm/models/N (its first mapper seed's); both are read with pycolmap, as a user opens them.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from e3cm_bench.sfm.consensus import RelativePose
from e3cm_bench.sfm.mapper import MODELS, Reconstruction, model_of
from e3cm_bench.sfm.metrics import relative_from_absolute
from e3cm_bench.sfm.uncalibrated import SPARSE

# Where a run keeps its models: reconstruct's (the folder a user opens), then sfm's.
MODEL_FOLDERS = (SPARSE, f"sfm/{MODELS}")


@dataclass(frozen=True)
class RunPoses:
    """One run's pairs (their names and their two views) and each pair's relative pose in the run's
    reconstruction (None: not both images in one model)."""

    names: list[str]
    views: list[tuple[str, str]]
    poses: list[RelativePose | None]


def models_folder(run: Path) -> Path | None:
    """The folder of the run's models (one sub-folder per model), None where it made none."""
    for name in MODEL_FOLDERS:
        if (Path(run) / name).is_dir():
            return Path(run) / name
    return None


def read_models(folder: Path | None, images: Sequence[str]) -> Reconstruction:
    """The models under `folder` (largest first, as the mapper ranks them) over `images`."""
    from e3cm_bench.ground.pycolmap import pycolmap_module

    if folder is None:
        return Reconstruction(list(images), [])
    pycolmap = pycolmap_module()
    found = [model_of(int(p.name), pycolmap.Reconstruction(str(p)))
             for p in sorted(Path(folder).iterdir(), key=lambda p: p.name) if p.is_dir() and p.name.isdigit()]
    found.sort(key=lambda m: (-len(m.poses), m.index))
    return Reconstruction(list(images), found)


def pair_poses(found: Reconstruction, views: Sequence[tuple[str, str]]) -> list[RelativePose | None]:
    """Each pair's relative pose in `found` (sfm.metrics' rule: both images in one model)."""
    poses = []
    for view0, view1 in views:
        placed0, placed1 = found.placed(view0, view1)
        if placed0 is None or placed1 is None or placed0[0] != placed1[0]:
            poses.append(None)
        else:
            poses.append(RelativePose(*relative_from_absolute(placed0[1], placed1[1])))
    return poses


def run_poses(run: Path) -> RunPoses:
    """A finished run's pairs, as its record loads them, and their poses in its models."""
    from e3cm_bench.benchmarks.from_record import load_run_pairs

    pairs = load_run_pairs(run).pairs
    views = [(str(p.view0), str(p.view1)) for p in pairs]
    images = sorted({name for pair in views for name in pair})
    return RunPoses([p.name for p in pairs], views, pair_poses(read_models(models_folder(run), images), views))


def common_poses(runs: Mapping[str, RunPoses]) -> dict[str, list[RelativePose | None]]:
    """label -> poses of the pairs every run holds, in the first run's order, by the pairs' views
    (runs of one folder under different pair graphs are compared on the pairs they share)."""
    if not runs:
        return {}
    first = next(iter(runs.values()))
    shared = [v for v in first.views if all(v in set(r.views) for r in runs.values())]
    out = {}
    for label, run in runs.items():
        where = {v: k for k, v in enumerate(run.views)}
        out[label] = [run.poses[where[v]] for v in shared]
    return out
