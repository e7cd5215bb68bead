"""The multi-view protocol: what is made of a run's matches before a pair is scored.

Measured on the same cached matches (docs/sfm.md, "The protocol"), the multi-view verdict
moves more with these choices than with the matcher, so each is an evaluation option
(benchmarks/eval_options.py: the same matches scored again under another protocol, --eval-only
may change it), recorded in config.yaml's evaluation block and in each run's summary.csv:

- mapper: ``global`` (pycolmap.global_mapping, GLOMAP) or ``incremental``
  (pycolmap.incremental_mapping, COLMAP's; hloc's);
- mapper_seeds: how many reconstructions (seeds evaluation.seed + 0..K-1) from the same
  database, each pair scored in each: the mapper's own randomness enters the interval;
- merge: how the keypoints of an image are merged across its pairs into tracks
  (interchange/tracks.py): ``auto`` (the matcher's kind: ``exact`` for detections, a radius of
  DENSE_MERGE_PX for the others), ``exact``, ``radius`` (merge_px), or ``quantize`` (hloc's
  dense quantization: cell QUANTIZE_CELL px, max error QUANTIZE_MAX_ERROR px);
- verification: ``estimator`` (the pose benchmarks' essential-matrix RANSAC inliers as the
  two-view geometries) or ``colmap`` (pycolmap.verify_matches, COLMAP's own, hloc's options);
- score_model: ``any`` (a pair from whichever model holds both images) or ``largest`` (IMC's:
  the largest model of the pair's bag only).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from e3cm_bench.datasets.base import DatasetError

MAPPERS = ("global", "incremental")
MERGES = ("auto", "exact", "radius", "quantize")
BY_COLMAP = "colmap"  # the verification by COLMAP's own two-view geometry (reconstruct's, always)
VERIFICATIONS = ("estimator", BY_COLMAP)
SCORE_MODELS = ("any", "largest")
# The merge radius of a matcher whose keypoints are not detections (dense, semi-dense, sub-pixel
# refined): issue 60's grid chose 2 px (within 1 px most tracks stay at two views; hloc's 4 px
# quantization then cost e3cm-plus). Remade with per-seed verification (docs/sfm.md, the grid),
# the quantization is level with it or above under the global mapper, within the intervals.
DENSE_MERGE_PX = 2.0
QUANTIZE_CELL, QUANTIZE_MAX_ERROR = 4.0, 4.0  # hloc's dense matching defaults
DEFAULT_SEEDS = 3


@dataclass(frozen=True)
class ReconstructionProtocol:
    """The protocol as the user set it (merge may still be ``auto``: `resolved` settles it)."""

    mapper: str = "global"
    mapper_seeds: int = DEFAULT_SEEDS
    merge: str = "auto"
    merge_px: float | None = None
    verification: str = "estimator"
    score_model: str = "any"

    def resolved(self, detections: bool | None) -> "ReconstructionProtocol":
        """``auto`` made concrete for a matcher whose keypoints are detections (True), are not
        (False) or of unknown kind (None: treated as not, the safer error: a merge of 2 px
        costs detections little, exact merging costs dense matches their tracks)."""
        merge, radius = self.merge, self.merge_px
        if merge == "auto":
            if radius is not None:  # --merge-px given alone
                merge = "radius" if radius > 0 else "exact"
            else:
                merge = "exact" if detections else "radius"
        if merge == "radius":
            radius = DENSE_MERGE_PX if radius is None else radius
            if radius == 0:
                merge = "exact"
        if merge == "exact":
            radius = 0.0
        elif merge == "quantize":
            radius = QUANTIZE_CELL
        return ReconstructionProtocol(self.mapper, self.mapper_seeds, merge, float(radius), self.verification,
                                      self.score_model)

    def merge_label(self) -> str:
        if self.merge == "radius":
            return f"radius {self.merge_px:g}"
        if self.merge == "quantize":
            return f"quantize cell {QUANTIZE_CELL:g} max error {QUANTIZE_MAX_ERROR:g}"
        return self.merge

    def record(self) -> dict:
        return asdict(self)


def _whole(value, flag: str, most: int | None = None) -> int:
    """A whole number >= 1 (and <= most, where given); one line naming the flag otherwise."""
    try:
        k = int(str(value))
    except ValueError:
        raise DatasetError(f"{flag} must be a whole number, got {value!r}") from None
    if k < 1:
        raise DatasetError(f"{flag} must be at least 1, got {k}")
    if most is not None and k > most:
        raise DatasetError(f"{flag} must be 1..{most}, got {k}")
    return k


def keypoints_are_detections(matcher: str | None) -> bool | None:
    """What the matcher's registry entry declares (MatcherEntry.keypoints_are_detections), or
    None when the name resolves to no registered matcher (a plugin not installed here)."""
    if not matcher:
        return None
    from e3cm_bench.matchers.registry import get_matcher

    try:
        entry = get_matcher(matcher)
    except ValueError:
        return None
    return bool(entry.keypoints_are_detections)


def protocol_of(ev) -> ReconstructionProtocol:
    """The protocol of a run's evaluation settings (EvalSettings' reconstruction fields, which
    Benchmark.resolve_eval fills from the benchmark's eval_defaults where the user gives none).
    Settings made by hand without one (the Python API's EvalSettings()) are mapped as the toolkit's
    first sfm benchmark did: the incremental mapper once, keypoints merged exactly."""
    if ev.mapper is None:
        return ReconstructionProtocol(mapper="incremental", mapper_seeds=1, merge="exact")
    default = ReconstructionProtocol()
    return ReconstructionProtocol(ev.mapper, ev.mapper_seeds or default.mapper_seeds, ev.merge or default.merge,
                                  ev.merge_px, ev.verification or default.verification,
                                  ev.score_model or default.score_model)


def __getattr__(name: str):
    from e3cm_bench.ground.moved import renamed

    return renamed(__name__, name)  # a name renamed here (ground/moved.py RENAMED), else AttributeError
