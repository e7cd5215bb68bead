"""The sfm results of docs/sfm.md: every built-in method (CNN ones on efficientnet_lite0) on a
multi-view set, matched together (each image through the backbone once for all methods), each
into OUT/SET/METHOD, then the set's table in OUT/SET/table.{csv,md}.

    python scripts/sfm_results.py kitti --out /tmp/sfm-results
    python scripts/sfm_results.py synth --out /tmp/sfm-results

kitti: the shared KITTI 00 frames (../shared/data/megadepth_test_1500, kitti00_seq.npz), pair
synth: the room scene rendered from 10 views (e3cm_bench/synth/multiview.py, written under
OUT/data). Both with the pair graph a sequential window of 3 (each image with the next 3).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from e3cm_bench.benchmarks import EvalSettings, get_benchmark
from e3cm_bench.demo import BACKBONE, METHODS
from e3cm_bench.experiments import write_table
from e3cm_bench.method import MethodSpec
from e3cm_bench.runner import run_methods

SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "megadepth_test_1500"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("set", choices=("kitti", "synth"))
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--methods", nargs="*", default=list(METHODS))
    parser.add_argument("--window", type=int, default=3, help="the pair graph's window (default 3)")
    parser.add_argument("--views", type=int, default=10, help="synth's number of views (default 10)")
    args = parser.parse_args()
    bench = get_benchmark("sfm")
    if args.set == "kitti":
        root, options = SHARED, {"scene_info": SHARED / "scene_info" / "kitti00_seq.npz", "window": str(args.window)}
    else:
        from e3cm_bench.synth.multiview import write_multiview

        root = args.out / "data" / "room"
        options = {"scene_info": write_multiview(root, n_views=args.views), "window": str(args.window)}
    dataset = bench.load_dataset(root, **options)
    out = args.out / args.set
    runs = [(out / label, MethodSpec.create(backbone=BACKBONE, max_side=bench.max_side(None), seed=0, label=label,
                                            **METHODS[label]))
            for label in args.methods]
    run_methods(bench, runs, dataset, ev=EvalSettings(seed=0),
                dataset_load={"root": str(Path(root).resolve()), "skip_bad": False,
                              "options": {k: str(v) for k, v in options.items()}})
    write_table([run_dir for run_dir, _ in runs], out / "table", paper_rows=False, compare=False)


if __name__ == "__main__":
    main()
