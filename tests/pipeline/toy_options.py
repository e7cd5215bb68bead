"""A fresh process that adds one toy option to each table (method, evaluation, dataset) and runs a
real benchmark with them end to end, then reruns it (tests/pipeline/test_toy_options.py).

The options are declared the way docs/development.md's recipes say, in their tables and nowhere
else; nothing of the toolkit is replaced. It runs in its own interpreter so that the tables of the
test session stay as shipped.

    python tests/pipeline/toy_options.py HPATCHES_ROOT OUT
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

from e3cm_bench.benchmarks import get_benchmark, register
from e3cm_bench.benchmarks.base import DatasetOption
from e3cm_bench.benchmarks.eval_options import EVAL_OPTIONS, PIXELS, EvalOption
from e3cm_bench.datasets.hpatches import HPatches
from e3cm_bench.method.options import METHOD_OPTIONS, MethodOption

# A method option that is a setting of the matchers that have it (SIFT's max_keypoints).
METHOD_OPTIONS["max_keypoints"] = MethodOption("max_keypoints", ("--max-keypoints",), "whole", None,
                                               "Toy: the strongest keypoints kept.", concerns="setting")
# An evaluation option filling a field the metrics read (the homography RANSAC's threshold).
EVAL_OPTIONS["toy_ransac_px"] = EvalOption("toy_ransac_px", "--toy-ransac-px", "number", None,
                                           "Toy: the homography RANSAC threshold.", field="homography_ransac_px",
                                           range=PIXELS)


class ToySequences(HPatches):
    """HPatches with a toy dataset option: the one sequence to keep (its reader: the consumer)."""

    def __init__(self, root, exclude_large: bool = False, sequences=None, skip_bad: bool = False,
                 toy_sequence: str | None = None) -> None:
        super().__init__(root, exclude_large, [toy_sequence] if toy_sequence else sequences, skip_bad)


hpatches = get_benchmark("hpatches")
register(replace(hpatches, name="toy-hpatches", dataset=ToySequences, dataset_options=(
    *hpatches.dataset_options, DatasetOption("toy_sequence", "text", "Toy: the one sequence kept."))))

if __name__ == "__main__":
    import yaml

    from e3cm_bench.cli import app  # its commands are made from the tables as they are now
    from e3cm_bench.pipeline.experiments import load_experiment

    root, out = sys.argv[1], Path(sys.argv[2])
    # each is a key of an experiment config, checked by its kind
    config = out / "toy.yaml"
    config.write_text(yaml.safe_dump({"benchmark": "toy-hpatches", "dataset": {"toy_sequence": "v_boat"},
                                      "evaluation": {"toy_ransac_px": 2.0},
                                      "methods": [{"matcher": "sift", "max_keypoints": 30}]}))
    assert load_experiment(config)["methods"][0]["max_keypoints"] == 30
    config.write_text(yaml.safe_dump({"benchmark": "toy-hpatches", "methods": [{"matcher": "sift",
                                                                                "max_keypoints": "x"}]}))
    try:
        load_experiment(config)
        raise AssertionError("a word for a whole number was taken")
    except ValueError as error:
        assert "'max_keypoints' must be a whole number" in str(error), error
    common = ["--root", root, "--matcher", "sift", "--max-side", "320", "--limit", "2"]
    for args in (["toy-hpatches", *common, "--out", str(out / "toy"), "--max-keypoints", "60",
                  "--toy-ransac-px", "1.5", "--toy-sequence", "v_graffiti"],
                 ["toy-hpatches", *common, "--out", str(out / "plain"), "--set", "max_keypoints=60",
                  "--ransac-px", "1.5", "--sequences", "v_graffiti"],
                 ["rerun", str(out / "toy"), "--out", str(out / "again")]):
        try:
            app(args, standalone_mode=False)
        except SystemExit as stop:
            if stop.code:
                raise
