"""The multi-view protocol: what is made of a run's matches before a pair is scored.

Measured on the same cached matches (docs/sfm.md, "The protocol"), the multi-view verdict
moves more with these choices than with the matcher, so each is a setting, recorded in
config.yaml (dataset.protocol, dataset.reconstruction) and in each run's summary.csv:

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


# Upper bounds, checked before anything loads. Each mapper seed is a whole reconstruction (and its
# verification): 10^9 of them were accepted and the kernel killed the run at 21.7 GB after matching;
# 100 is hours on a large set already. A merge radius is a keypoint's localisation error; beyond
# 50 px it merges distinct points of one image into one (10^9 merged every keypoint and still
# reported every image registered).
MAX_MAPPER_SEEDS = 100
MAX_MERGE_PX = 50.0


def parse_protocol(mapper=None, mapper_seeds=None, merge=None, merge_px=None, verification=None,
                   score_model=None) -> ReconstructionProtocol:
    """The dataset options' text as a ReconstructionProtocol; bad values in one line (DatasetError)."""
    default = ReconstructionProtocol()
    seeds = default.mapper_seeds if mapper_seeds is None else _whole(mapper_seeds, "--mapper-seeds", MAX_MAPPER_SEEDS)
    return ReconstructionProtocol(_choice(mapper, MAPPERS, "--mapper", default.mapper), seeds,
                    _choice(merge, MERGES, "--merge", default.merge), _radius(merge_px),
                    _choice(verification, VERIFICATIONS, "--verification", default.verification),
                    _choice(score_model, SCORE_MODELS, "--score-model", default.score_model))


def _choice(value, choices: tuple[str, ...], flag: str, default: str) -> str:
    if value is None:
        return default
    text = str(value).strip().lower()
    if text not in choices:
        raise DatasetError(f"{flag} must be one of {', '.join(choices)}, got {value!r}")
    return text


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


def _radius(value) -> float | None:
    if value is None:
        return None
    try:
        radius = float(str(value))
    except ValueError:
        raise DatasetError(f"--merge-px must be a radius in pixels, got {value!r}") from None
    if not 0 <= radius <= MAX_MERGE_PX:
        raise DatasetError(f"--merge-px must be 0..{MAX_MERGE_PX:g} pixels, got {value}")
    return radius


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


def set_protocol(pairs) -> ReconstructionProtocol:
    """The protocol a set's pairs carry (views.ViewPair.setup, as the set's options gave it; the
    same for every pair). Pairs without one (built by hand, for the Python API) are mapped as the
    toolkit's first sfm benchmark did: the incremental mapper once, keypoints merged exactly."""
    for pair in pairs:
        setup = getattr(pair, "setup", None)
        if isinstance(setup, ReconstructionProtocol):
            return setup
    return ReconstructionProtocol(mapper="incremental", mapper_seeds=1, merge="exact")


def __getattr__(name: str):
    from e3cm_bench.ground.moved import renamed

    return renamed(__name__, name)  # a name renamed here (ground/moved.py RENAMED), else AttributeError
