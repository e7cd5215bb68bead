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


@dataclass(frozen=True)
class EvalOption(KindOf):
    """name: the config key and the command's parameter; flag: its spelling on the command line;
    kind: a key of options.KINDS; default: the value when none is given (None: the protocol's,
    else the benchmark's); field: the EvalSettings field it fills (its name where not given;
    `ransac_px` is the benchmark's own threshold field, Benchmark.ransac_field); show_default:
    what --help says the default is, where the value itself says nothing;
    range: the values a number kind allows besides its kind (options.Range; None: any of the kind)."""

    name: str
    flag: str
    kind: str
    default: object
    help: str
    field: str = ""
    show_default: str | None = None
    range: Range | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.field:
            object.__setattr__(self, "field", self.name)


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
)}


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


def check_eval_given(given: Mapping, refused: Mapping[str, tuple[tuple, str]], where: str = "") -> dict:
    """Evaluation options by name (a command's flags, a config's ``evaluation:``, a record's given, the
    Python API's keywords) -> the ones given (None: not given), each checked: an unknown name is one
    line with the nearest, a value by its flag's kind and range, a name the benchmark refuses
    (`refused`: name -> (the values it still takes, why)) by its reason."""
    from e3cm_bench.ground.suggest import did_you_mean

    for name in given:
        if name not in EVAL_OPTIONS:
            raise ValueError(f"{where}{name!r} is not an evaluation option{did_you_mean(name, EVAL_OPTIONS)}; "
                             f"they are {', '.join(EVAL_OPTIONS)}")
    for name, value in given.items():
        EVAL_OPTIONS[name].check(value, f"{where}{name}" if where else None)
        if name in refused and value not in refused[name][0]:
            raise ValueError(refused[name][1])
    return {name: value for name, value in given.items() if value is not None}
