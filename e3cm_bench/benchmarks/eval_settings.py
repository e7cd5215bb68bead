"""What changes a run's metrics and never its matches: `EvalSettings`, the evaluation block of
a run's config.yaml.

Its fields are the evaluation options' (eval_options.py EVAL_OPTIONS: each option names the
field it sets, its kind and range, the benchmarks that take it); a benchmark resolves them from
its protocol, the user's values and its own defaults (Benchmark.resolve_eval), and the evaluate
stage reads them. `--eval-only` may change them on a run already matched.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields

from e3cm_bench.benchmarks.eval_options import RECONSTRUCTION_FIELDS, check_settings
from e3cm_bench.geometry import metrics


MAX_INTERVAL_SEEDS = 20  # each seed is one more evaluation of every pair
MAX_REPEATS = 100  # --repeats: each is one more evaluation of every pair (RoMa reports 5, the IMC code 3)


@dataclass(frozen=True)
class EvalSettings:
    """Everything that changes only the metrics, never the matches (`--eval-only` may change it).

    PROTOCOLS §2-3. ``seed`` seeds every evaluation RANSAC, right before it runs.
    """

    seed: int = 0
    homography_ransac_px: float = 3.0
    homography_max_iters: int = 5000
    homography_confidence: float = 0.9999
    # HPatches: the pixel convention the ground-truth H is applied in: "center" (ours, PROTOCOLS
    # §2) or "corner", glue-factory's (its keypoints are in the corner convention and its H
    # error takes them as they are: --protocol gluefactory); and glue-factory's match precision
    # (symmetric H error below t px: prec@t px per pair) at these thresholds, none by default.
    homography_pixel_origin: str = "center"
    match_precision_px: tuple[float, ...] = ()
    pose_ransac_px: float = 0.5
    # The pixels pose_ransac_px is in: "original" (the stored images, PROTOCOLS §3) or "matched"
    # (the images as resized for matching, SuperGlue's: 1 px at its 1600 px).
    pose_ransac_frame: str = "original"
    pose_confidence: float = 0.99999
    precision_thresholds: tuple[float, ...] = metrics.PRECISION_THRESHOLDS
    correct_px: float = 3.0  # --viz: a homography match is drawn green within this reprojection error
    protocol: str = "default"  # method/protocols.py; a non-default one also sets the method's resize etc.
    drop_failures: bool = False  # pose pairs without an estimate leave the AUC (protocol e3cm-release)
    # The robust estimator of the evaluation's H and relative pose: opencv or poselib (estimators.py).
    estimator: str = "opencv"
    # wxbs and evd (benchmarks/wxbs.py, evd.py): OpenCV's robust method for the evaluation's F and
    # EVD's H, ransac or magsac (USAC MAGSAC++, wxbs-benchmark's estimator: --protocol wxbs); the
    # pose benchmarks' E too (ransac, magsac, or accurate: USAC_ACCURATE; the sweep's cells); and
    # the F estimator's threshold (pixels), confidence and iterations. HPatches' H stays RANSAC.
    opencv_method: str = "ransac"
    fundamental_ransac_px: float = 1.0
    fundamental_confidence: float = 0.999
    fundamental_max_iters: int = 100000
    # --repeats K: the estimation rerun K times with seeds seed, seed+1, ... (no rematching); the
    # summary is the mean over the repeats with each metric's spread (evaluate.py), as RoMa (5)
    # and the Image Matching Challenge code (3) report it.
    repeats: int = 1
    # The RANSAC seeds the interval holds (seed, seed+1, ...): each bootstrap resample of the pairs
    # takes one of them, so the interval holds the estimation's spread beside the pairs'; the
    # run's numbers stay its own seed's (a one-evaluation interval where 1). The commands'
    # default is the benchmark's default_interval_seeds under e3cm-bench's protocol.
    interval_seeds: int = 1
    # A reconstruction's protocol (sfm, reconstruct: sfm/protocol.py, each an evaluation option of
    # theirs); None where the benchmark reconstructs nothing, left out of its record (`record`).
    mapper: str | None = None
    mapper_seeds: int | None = None
    merge: str | None = None
    merge_px: float | None = None
    verification: str | None = None
    score_model: str | None = None

    def __post_init__(self) -> None:
        from e3cm_bench.geometry.estimators import POSE_METHODS, check_estimator

        check_settings({f.name: getattr(self, f.name) for f in fields(self)})  # kinds and ranges, first
        check_estimator(self.estimator)
        if self.homography_pixel_origin not in ("center", "corner"):
            raise ValueError(f"homography_pixel_origin must be center or corner, got {self.homography_pixel_origin!r}")
        if self.opencv_method not in POSE_METHODS:  # accurate: the relative pose's only (USAC_ACCURATE)
            raise ValueError(f"opencv_method must be one of {', '.join(POSE_METHODS)}, got {self.opencv_method!r}")
        if not 1 <= int(self.repeats) <= MAX_REPEATS:
            raise ValueError(f"--repeats must be 1 to {MAX_REPEATS}, got {self.repeats}")
        if not 1 <= int(self.interval_seeds) <= MAX_INTERVAL_SEEDS:
            raise ValueError(f"--interval-seeds must be 1 to {MAX_INTERVAL_SEEDS}, got {self.interval_seeds}")

    @classmethod
    def from_record(cls, record: Mapping | None, **changes) -> EvalSettings:
        """The settings as a run folder's config.yaml records them (its `evaluation` block; YAML
        lists back to tuples, defaults for fields an older record lacks, unknown keys ignored),
        with `changes` applied (another seed for a rerun)."""
        names = cls.record_keys()
        values = {k: tuple(v) if isinstance(v, list) else v for k, v in dict(record or {}).items() if k in names}
        return cls(**{**values, **changes})

    def record(self) -> dict:
        """The `evaluation` block of config.yaml: every field, a reconstruction's only where there is one."""
        return {k: v for k, v in asdict(self).items() if self.mapper is not None or k not in RECONSTRUCTION_FIELDS}

    @classmethod
    def record_keys(cls) -> set[str]:
        """The keys of the `evaluation` block this version reads."""
        return {f.name for f in fields(cls)}
