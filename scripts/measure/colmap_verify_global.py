"""COLMAP's verification before the global mapper (issue 69): the shared KITTI frames' cached
sfm matches reconstructed under --verification colmap with COLMAP's default
max_H_inlier_ratio (0.8) and with 1.0, for both mappers and each merge given; AUC@10 and how
many pairs COLMAP labelled planar or panoramic (pycolmap.TwoViewGeometryConfiguration).

    python scripts/measure/colmap_verify_global.py --runs /work/sfmruns/kitti --scratch /tmp/verify \
        --methods sift e3cm-plus --window 2

RUNS/METHOD is only read (sfm_results.py kitti made it); each cell is evaluated on a copy under
SCRATCH/RATIO/MAPPER-MERGE/METHOD (sfm_protocol_grid.evaluate_copy: a finished cell is read back).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "results"))
from sfm_protocol_grid import evaluate_copy  # noqa: E402

from e3cm_bench.ground.pycolmap import pycolmap_module  # noqa: E402
from e3cm_bench.sfm import mapper as reconstruct  # noqa: E402

MERGES = {"exact": {"merge": "exact"}, "merge2": {"merge": "radius", "merge_px": 2.0}}


def planar_pairs(database: Path) -> tuple[int, int]:
    pycolmap = pycolmap_module()  # never imported before PIL (interchange/colmap.py says why)

    planar = {int(pycolmap.TwoViewGeometryConfiguration.PLANAR_OR_PANORAMIC),
              int(pycolmap.TwoViewGeometryConfiguration.PLANAR), int(pycolmap.TwoViewGeometryConfiguration.PANORAMIC)}
    with pycolmap.Database.open(str(database)) as db:
        geometries = db.read_two_view_geometries()[1]
    return sum(int(g.config) in planar for g in geometries), len(geometries)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=Path, required=True)
    parser.add_argument("--scratch", type=Path, required=True)
    parser.add_argument("--methods", nargs="*", default=["sift", "e3cm-plus"])
    parser.add_argument("--ratios", nargs="*", type=float, default=[0.8, 1.0])
    parser.add_argument("--mappers", nargs="*", default=["global", "incremental"])
    parser.add_argument("--merges", nargs="*", default=list(MERGES))
    parser.add_argument("--window", type=int, default=None, help="the pair graph's window (default: the runs')")
    args = parser.parse_args()
    print("ratio,mapper,merge,method,auc@10,auc@10_lo,auc@10_hi,registered_images,planar_pairs,verified_pairs",
          flush=True)
    for ratio in args.ratios:
        reconstruct.VERIFY_OPTIONS["max_H_inlier_ratio"] = ratio
        for mapper in args.mappers:
            for merge in args.merges:
                for method in args.methods:
                    target = args.scratch / f"{ratio:g}" / f"{mapper}-{merge}" / method
                    protocol = {"mapper": mapper, "verification": "colmap", **MERGES[merge],
                                **({"window": str(args.window)} if args.window else {})}
                    summary = evaluate_copy(args.runs / method, target, protocol)
                    planar, verified = planar_pairs(target / "sfm" / "database.db")
                    print(f"{ratio:g},{mapper},{merge},{method},{summary['auc@10']:.2f},{summary['auc@10_lo']:.2f},"
                          f"{summary['auc@10_hi']:.2f},{summary['registered_images']:.1f},{planar},{verified}",
                          flush=True)


if __name__ == "__main__":
    main()
