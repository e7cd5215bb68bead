"""Where e3cm-plus's automatic prewarp fires, and what it does there.

    python scripts/results/prewarp_report.py RUN_PLUS RUN_UNWARPED [--csv OUT.csv]

RUN_PLUS: an e3cm-plus run folder; RUN_UNWARPED: the same pairs matched without the prewarp
(`e3cm-ransac`, which is e3cm-plus with prewarp false: the direct pipeline is the RANSAC
cascade). For each pair of RUN_PLUS's dataset (read from its config.yaml), the images are
resized as the run resized them, the pyramids computed, and DFM's stage 0 run as e3cm-plus
runs it (e3cm_plus.prewarp_decision): the decision, the stage-0 homography's rotation and
scales at B's centre, and its inlier share. Beside them, each run's per-pair error from its
per_pair.csv (HPatches: h_error in px; pose: err_pose in degrees). Prints how often the
prewarp fires and, on those pairs, the error with it and without it.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from e3cm_bench.benchmarks.from_record import benchmark_of, dataset_source
from e3cm_bench.ground.images import load_image, resize_max_side
from e3cm_bench.matchers.e3cm_plus import E3CMPlusMatcher, prewarp_decision
from e3cm_bench.method.spec import MethodSpec
from e3cm_bench.storage import RunConfig, RunFolder


def read_run(folder: Path) -> tuple[RunConfig, pd.DataFrame]:
    run = RunFolder(folder)
    return run.run_config(), pd.read_csv(run.per_pair_path).set_index("pair")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_plus", type=Path)
    parser.add_argument("run_unwarped", type=Path)
    parser.add_argument("--csv", type=Path)
    args = parser.parse_args()
    config, plus = read_run(args.run_plus)
    _, unwarped = read_run(args.run_unwarped)
    identity = config.identity
    spec = MethodSpec.create(identity["matcher"], identity["backbone"], weights=identity.get("weights"), max_side=identity.get("max_side"),
                             resize=identity.get("resize", "shrink"), options=identity.get("settings") or {})
    matcher = spec.build("cpu")
    if not isinstance(matcher, E3CMPlusMatcher):
        raise SystemExit(f"{args.run_plus}: an e3cm-plus run is needed, this one is {identity['matcher']}")
    benchmark = benchmark_of(config)
    # its dataset_load, else (a run given its pairs as a list: the demo) its dataset block; every pair
    # the run could have matched (skip_bad), whatever the run recorded
    root, _, options = dataset_source(config, benchmark)
    dataset = benchmark.load_dataset(root, skip_bad=True, **options)
    error = "h_error" if "h_error" in plus.columns else "err_pose"
    rows = []
    for pair in dataset:
        if pair.name not in plus.index:
            continue
        images = []
        for path, turns in zip((pair.image0, pair.image1), pair.rotations):
            image = load_image(path)
            if spec.upright and turns:
                image = np.ascontiguousarray(np.rot90(image, turns))
            images.append(resize_max_side(image, spec.max_side, spec.resize)[0])
        feats0, feats1, _ = matcher.pyramids(*images)
        size0, size1 = ((im.shape[1], im.shape[0]) for im in images)
        _, info = prewarp_decision(feats0, feats1, size0, size1, matcher.settings)
        rows.append({"pair": pair.name, "warped": info["prewarp"] == "warped", "decision": info["prewarp"],
                     "rotation_deg": info.get("rotation_deg"), "scale_big": info.get("scale_big"),
                     "scale_small": info.get("scale_small"),
                     "stage0_inlier_share": info["stage0_inliers"] / max(info["stage0_matches"], 1),
                     f"{error} (e3cm-plus)": plus.loc[pair.name, error], f"{error} (unwarped)": unwarped.loc[pair.name, error]})
        print(f"{pair.name}: {info['prewarp']}", flush=True)
    table = pd.DataFrame(rows)
    fired = table[table["warped"]]
    print(f"\n{config.benchmark} ({args.run_plus}): the prewarp fires on {len(fired)} of {len(table)} pairs")
    if len(fired):
        a, b = fired[f"{error} (e3cm-plus)"], fired[f"{error} (unwarped)"]
        print(f"on those pairs, {error} median {a.median():.2f} with it, {b.median():.2f} without; "
              f"better on {(a < b).sum()}, worse on {(a > b).sum()}, equal on {(a == b).sum()}")
        print(fired.drop(columns=["decision"]).to_string(index=False, float_format=lambda v: f"{v:.2f}"))
    if args.csv:
        args.csv.parent.mkdir(parents=True, exist_ok=True)
        table.to_csv(args.csv, index=False)


if __name__ == "__main__":
    main()
