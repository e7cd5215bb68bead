"""The evaluation's options, declared once as data, as the method's are (method/options.py).

Each `EvalOption` is the one declaration of an option that changes only how a run is scored:
the benchmark commands' flag and help come from it (cli/benchmarks.py), an experiment config's
``evaluation:`` section takes its name as a key, checked against its kind (pipeline/experiments.py),
and both hand the values to `Benchmark.resolve_eval` under its `keyword`. A new evaluation flag
is one entry here and the code that reads its EvalSettings field.

The seed and the protocol are method options (they also decide the matches where a matcher is
random or resized): they are not here. This module imports nothing heavy (`--help` reads it).
"""

from __future__ import annotations

from dataclasses import dataclass

from e3cm_bench.method.options import KindOf


@dataclass(frozen=True)
class EvalOption(KindOf):
    """name: the config key and the command's parameter; flag: its spelling on the command line;
    kind: a key of options.KINDS; default: the value when none is given (None: the protocol's,
    else the benchmark's); keyword: Benchmark.resolve_eval's parameter it fills (its name where
    not given); show_default: what --help says the default is, where the value itself says nothing."""

    name: str
    flag: str
    kind: str
    default: object
    help: str
    keyword: str = ""
    show_default: str | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.keyword:
            object.__setattr__(self, "keyword", self.name)


EVAL_OPTIONS: dict[str, EvalOption] = {o.name: o for o in (
    EvalOption("ransac_px", "--ransac-px", "number", None,
               "Threshold of the evaluation RANSAC in px (HPatches 3, pose 0.5)."),
    EvalOption("pose_estimator", "--pose-estimator", "text", None,
               "Robust estimator of the evaluation (relative pose; HPatches: the homography): opencv (default), "
               "poselib (pip install 'e3cm-bench\\[poselib]') or pycolmap (COLMAP's LO-RANSAC; "
               "'e3cm-bench\\[colmap]'); --eval-only may change it.", keyword="estimator"),
    EvalOption("repeats", "--repeats", "whole", 1,
               "Run the evaluation's RANSAC K times (seeds SEED..SEED+K-1, no rematching): the summary is their "
               "mean, with each metric's spread (_sd); at most 100."),
    EvalOption("interval_seeds", "--interval-seeds", "whole", None,
               "RANSAC seeds the interval holds (SEED..SEED+K-1; each resample of the pairs takes one): the "
               "numbers stay SEED's, the interval holds the estimation's spread too. 1: the pairs' only.",
               show_default="3 under e3cm-bench's protocol, 1 under a reference's"),
)}


def eval_keywords(given: dict) -> dict:
    """Evaluation options by name (a command's, a config's ``evaluation:``) -> Benchmark.resolve_eval's
    keywords; a value not given (None) is left out, so the protocol's or the benchmark's holds."""
    return {EVAL_OPTIONS[name].keyword: value for name, value in given.items() if value is not None}
