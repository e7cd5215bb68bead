"""The evaluation's options, declared once as data, as the method's are (method/options.py).

Each `EvalOption` is the one declaration of an option that changes only how a run is scored:
the benchmark commands' flag and help come from it (cli/benchmarks.py), an experiment config's
``evaluation:`` section takes its name as a key, checked against its kind (pipeline/experiments.py),
and both hand the values to `Benchmark.resolve_eval` as one mapping by these names; each option
names the EvalSettings field it fills. A new evaluation flag is one entry here and the code that
reads its field.

The seed and the protocol are method options (they also decide the matches where a matcher is
random or resized): they are not here. This module imports nothing heavy (`--help` reads it).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from e3cm_bench.ground.values import KindOf, Range, check_value

# The ranges of the evaluation's values (options.Range), each declared once: the flags below and
# the EvalSettings fields they fill (SETTING_VALUES) share them.
# A threshold in pixels: above 0 (OpenCV takes 0 or less as its own 3 px, while the record would say
# 0), and at most 1,000 px, past any image's diagonal this evaluates.
PIXELS = Range(0, 1000, low_open=True)
# A RANSAC confidence: a probability strictly between 0 and 1.
CONFIDENCE = Range(0, 1, low_open=True, high_open=True)
# RANSAC's iterations: at least 1, at most ten million (OpenCV's own cap is far beyond what ends).
ITERATIONS = Range(1, 10_000_000)
# A precision threshold (a fraction of the image's diagonal, or pixels): above 0.
POSITIVE = Range(0, None, low_open=True)


# Each mapper seed is a whole reconstruction (and its verification): 10^9 of them were accepted and
# the kernel killed the run at 21.7 GB after matching; 100 is hours on a large set already. A merge
# radius is a keypoint's localisation error; beyond 50 px it merges distinct points of one image into
# one (10^9 merged every keypoint and still reported every image registered).
RECONSTRUCTION_BOUNDS = {"mapper_seeds": Range(1, 100), "merge_px": Range(0, 50)}
# The benchmarks that reconstruct (sfm, and reconstruct's own images: sfm/own_images.py)
RECONSTRUCTING = ("sfm", "reconstruct")


@dataclass(frozen=True)
class EvalOption(KindOf):
    """name: the config key and the command's parameter; flag: its spelling on the command line;
    kind: a key of options.KINDS; default: the value when none is given (None: the protocol's,
    else the benchmark's); field: the EvalSettings field it fills (its name where not given;
    `ransac_px` is the benchmark's own threshold field, Benchmark.ransac_field); show_default:
    what --help says the default is, where the value itself says nothing;
    range: the values a number kind allows besides its kind (options.Range; None: any of the kind);
    choices: the words a text kind allows (none: any); benchmarks: the benchmarks that take it (none:
    every one), so that a reconstruction's options are on sfm's command and refused elsewhere."""

    name: str
    flag: str
    kind: str
    default: object
    help: str
    field: str = ""
    show_default: str | None = None
    range: Range | None = None
    choices: tuple[str, ...] = ()
    benchmarks: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.field:
            object.__setattr__(self, "field", self.name)

    def check(self, value, name: str | None = None) -> None:
        super().check(value, name)
        if value is not None and self.choices and value not in self.choices:
            raise ValueError(f"{name or self.flag} must be one of {', '.join(self.choices)}, got {value!r}")

    def applies_to(self, benchmark: str) -> bool:
        return not self.benchmarks or benchmark in self.benchmarks


EVAL_OPTIONS: dict[str, EvalOption] = {o.name: o for o in (
    EvalOption("ransac_px", "--ransac-px", "number", None,
               "Threshold of the evaluation RANSAC in px (HPatches 3, pose 0.5).", range=PIXELS),
    EvalOption("pose_estimator", "--pose-estimator", "text", None,
               "Robust estimator of the evaluation (relative pose; HPatches: the homography): opencv (default), "
               "poselib (pip install 'e3cm-bench\\[poselib]') or pycolmap (COLMAP's LO-RANSAC; "
               "'e3cm-bench\\[colmap]'); --eval-only may change it.", field="estimator"),
    EvalOption("repeats", "--repeats", "whole", 1,
               "Run the evaluation's RANSAC K times (seeds SEED..SEED+K-1, no rematching): the summary is their "
               "mean, with each metric's spread (_sd); at most 100."),
    EvalOption("interval_seeds", "--interval-seeds", "whole", None,
               "RANSAC seeds the interval holds (SEED..SEED+K-1; each resample of the pairs takes one): the "
               "numbers stay SEED's, the interval holds the estimation's spread too. 1: the pairs' only.",
               show_default="3 under e3cm-bench's protocol, 1 under a reference's"),
    # A reconstruction's protocol (sfm/protocol.py says what each does; its ReconstructionProtocol
    # holds the defaults, which each benchmark that reconstructs names in Benchmark.eval_defaults):
    # the evaluation of the same matches, so --eval-only may change them.
    EvalOption("mapper", "--mapper", "text", None,
               "global (pycolmap.global_mapping, GLOMAP) or incremental (pycolmap.incremental_mapping, COLMAP's).",
               show_default="global", choices=("global", "incremental"), benchmarks=RECONSTRUCTING),
    EvalOption("mapper_seeds", "--mapper-seeds", "whole", None,
               "Reconstructions from the same matches, seeds SEED..SEED+K-1, each verified and mapped again: every "
               "number is their mean, its interval over pairs and seeds (at most 100).",
               show_default="sfm 3, reconstruct 1", range=RECONSTRUCTION_BOUNDS["mapper_seeds"],
               benchmarks=RECONSTRUCTING),
    EvalOption("merge", "--merge", "text", None,
               "Keypoint merge: auto (exact for a matcher whose keypoints are detections, 2 px for the others), "
               "exact, radius (--merge-px, 2 by default) or quantize (hloc's dense quantization: cell 4 px, max "
               "error 4 px).", show_default="auto", choices=("auto", "exact", "radius", "quantize"),
               benchmarks=("sfm",)),
    EvalOption("merge_px", "--merge-px", "number", None,
               "Keypoints of an image within this radius (pixels) become one, so that tracks form from dense and "
               "semi-dense matches (at most 50).", show_default="0 for a matcher whose keypoints are detections, "
               "2 for the others (--merge auto)", range=RECONSTRUCTION_BOUNDS["merge_px"], benchmarks=RECONSTRUCTING),
    EvalOption("verification", "--verification", "text", None,
               "Two-view geometries: estimator (the benchmark's essential-matrix RANSAC inliers) or colmap "
               "(COLMAP's own verification, pycolmap.verify_matches).", show_default="sfm estimator, reconstruct "
               "colmap", choices=("estimator", "colmap"), benchmarks=("sfm",)),
    EvalOption("score_model", "--score-model", "text", None,
               "any (a pair from whichever model holds both images) or largest (IMC's: the largest model only).",
               show_default="any", choices=("any", "largest"), benchmarks=("sfm",)),
)}

# The EvalSettings fields of a reconstruction's protocol: those of the options only some benchmarks
# take; absent from the evaluation block of a benchmark that reconstructs nothing (EvalSettings.record).
RECONSTRUCTION_FIELDS = tuple(option.field for option in EVAL_OPTIONS.values() if option.benchmarks)


# What each EvalSettings field allows, kind and range (checked by check_settings, as a flag's value
# by its EvalOption): a record's evaluation block and a protocol's table give these fields as they
# are, so each is checked where the settings are made, whatever made them.
SETTING_VALUES: dict[str, tuple[str, Range | None]] = {
    # the field holds the flag's seed (SEEDS) plus a repeat's, an interval seed's or a mapper seed's
    # offset (seed + r): OpenCV's 32-bit limit, which SEEDS leaves room below
    "seed": ("whole", Range(0, 2**31 - 1)),
    **{f"{what}_ransac_px": ("number", PIXELS) for what in ("homography", "pose", "fundamental")},
    **{f"{what}_confidence": ("number", CONFIDENCE) for what in ("homography", "pose", "fundamental")},
    **{f"{what}_max_iters": ("whole", ITERATIONS) for what in ("homography", "fundamental")},
    "correct_px": ("number", PIXELS),
    "match_precision_px": ("numbers", PIXELS),
    "precision_thresholds": ("numbers", POSITIVE),
    **{name: ("text", None) for name in ("homography_pixel_origin", "pose_ransac_frame", "protocol", "estimator",
                                         "opencv_method")},
    "drop_failures": ("flag", None),
    # their ranges are EvalSettings' own bounds (MAX_REPEATS, MAX_INTERVAL_SEEDS), which name the flag
    "repeats": ("whole", None),
    "interval_seeds": ("whole", None),
}


def check_settings(values: Mapping) -> None:
    """Each evaluation setting of its kind and in its range (SETTING_VALUES; an empty list of
    thresholds is none), one line naming the first that is not."""
    for name, (kind, bounds) in SETTING_VALUES.items():
        value = values.get(name)
        if name in values and value != ():
            check_value(value, kind, bounds, name)
    for name, option in EVAL_OPTIONS.items():  # a reconstruction's (None where nothing is reconstructed)
        if option.benchmarks:
            option.check(values.get(option.field), option.field)


def check_eval_given(given: Mapping, refused: Mapping[str, tuple[tuple, str]], where: str = "",
                     benchmark: str = "") -> dict:
    """Evaluation options by name (a command's flags, a config's ``evaluation:``, a record's given, the
    Python API's keywords) -> the ones given (None: not given), each checked: an unknown name is one
    line with the nearest, a value by its flag's kind and range, an option of other benchmarks
    (EvalOption.benchmarks) or one `benchmark` refuses (`refused`: name -> (the values it still
    takes, why)) by its reason."""
    from e3cm_bench.ground.suggest import did_you_mean

    for name in given:
        if name not in EVAL_OPTIONS:
            raise ValueError(f"{where}{name!r} is not an evaluation option{did_you_mean(name, EVAL_OPTIONS)}; "
                             f"they are {', '.join(EVAL_OPTIONS)}")
    for name, value in given.items():
        option = EVAL_OPTIONS[name]
        option.check(value, f"{where}{name}" if where else None)
        if value is not None and benchmark and not option.applies_to(benchmark):
            raise ValueError(f"{where}{option.flag} is an evaluation option of {' and '.join(option.benchmarks)}, "
                             f"not of {benchmark}")
        if name in refused and value not in refused[name][0]:
            raise ValueError(refused[name][1])
    return {name: value for name, value in given.items() if value is not None}
