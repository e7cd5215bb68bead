"""How the ground-truth-free score (sfm/consensus.py) agrees with the ground truth, on finished runs of
several matchers over one set, the ground truth used only to judge the score:

    python scripts/validate/consensus_vs_truth.py RUN [RUN ...] [--csv OUT.csv] [--planar]

Multi-view runs (sfm, or reconstruct runs of the same images beside sfm runs of them): each run's
relative poses in its own reconstruction (models under RUN/sfm/models or RUN/sparse), the truth its
per_pair.csv's err_pose, both scored as AUC@10. --planar: homography runs (hpatches), each pair's H
estimated from the run's matches as its evaluation does, the truth its per_pair.csv's h_error scored
as the benchmark's h_acc@3 (the share within 3 px), the consensus error as `consensus.Planar`'s AUC
up to 10 px (a share within 3 px tied the ladder's worst rungs at 0; docs/own-images.md).

Prints both scores per run, Kendall's tau between them (scipy.stats), Spearman's rho per pair
between the true error and the consensus error (pooled over the runs), and every pair of runs that
both paired intervals (1000 resamples of the pairs, seed 0) separate in opposite directions.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from e3cm_bench.sfm import consensus  # noqa: E402
from e3cm_bench.sfm.verdict import run_poses  # noqa: E402
from e3cm_bench.stats.bootstrap import percentile_interval, resample_indices  # noqa: E402
from e3cm_bench.storage.folder import RunFolder  # noqa: E402


# The ladder (ladder.py's noise rungs beside SIFT), best first: it must come out in this order.
LADDER = ("sift", "ladder-noise_1px", "ladder-noise_2px", "ladder-noise_4px")


def posed(run: Path) -> tuple[list[str], list, np.ndarray]:
    found = run_poses(run)
    truth = pd.read_csv(RunFolder(run).per_pair_path).set_index("pair").loc[found.names, "err_pose"]
    return found.names, found.poses, truth.to_numpy(np.float64)


def planar(run: Path) -> tuple[list[str], list, np.ndarray]:
    """Each pair's H as the run's evaluation estimates it, as the corners it maps image 0's to."""
    from e3cm_bench.benchmarks.from_record import evaluation_of, load_run_pairs
    from e3cm_bench.storage.cache import MatchCache

    loaded = load_run_pairs(run)
    ev, cache = evaluation_of(loaded.config), MatchCache(RunFolder(run).matches_path)
    names, estimates = [], []
    for pair in loaded.pairs:
        matches = cache.read(pair.name)
        found = loaded.benchmark.two_view_geometry(pair, matches, ev)
        width, height = (int(v) for v in matches.info["size0"])
        names.append(pair.name)
        estimates.append(None if found is None else consensus.Planar.corners(found["H"], width, height))
    truth = pd.read_csv(RunFolder(run).per_pair_path).set_index("pair").loc[names, "h_error"]
    return names, estimates, truth.to_numpy(np.float64)


def within_3px(errors: np.ndarray) -> float:
    """The homography benchmark's h_acc@3 (percent): the ground truth's score of a planar run."""
    errors = np.asarray(errors, np.float64)
    errors = errors[~np.isnan(errors)]
    return float(100.0 * np.mean(errors <= 3.0)) if errors.size else float("nan")


def paired_interval(score, a: np.ndarray, b: np.ndarray, idx: np.ndarray) -> tuple[float, float]:
    return percentile_interval(np.array([score(a[r]) - score(b[r]) for r in idx]))


def main() -> None:
    from scipy import stats

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--csv", type=Path)
    parser.add_argument("--planar", action="store_true", help="homography runs (hpatches)")
    parser.add_argument("--set", default="", help="the set's name, for the CSV")
    args = parser.parse_args()
    read = planar if args.planar else posed
    judge = consensus.Planar() if args.planar else None
    score = judge.score if judge else consensus.score
    truth_score = within_3px if args.planar else consensus.score
    names, estimates, truth = None, {}, {}
    for run in args.runs:
        found_names, found, true_errors = read(run)
        if names is not None and found_names != names:
            raise SystemExit(f"{run}: its pairs differ from {args.runs[0]}'s")
        names, estimates[run.name], truth[run.name] = found_names, found, true_errors
    errors = (consensus.consensus_errors(estimates, judge.reference, judge.distance) if judge
              else consensus.consensus_errors(estimates))
    methods = list(estimates)
    table = pd.DataFrame({"method": methods, "truth": [truth_score(truth[m]) for m in methods],
                          "consensus": [score(errors[m]) for m in methods]})
    tau = stats.kendalltau(table["truth"], table["consensus"]).statistic
    both = np.concatenate([np.stack([truth[m], errors[m]], 1) for m in methods])
    both = both[~np.isnan(both).any(axis=1)]
    rho = stats.spearmanr(both[:, 0], both[:, 1]).statistic
    idx = resample_indices(len(names), 1000, 0)
    contradictions = []
    for i, a in enumerate(methods):
        for b in methods[i + 1:]:
            t_lo, t_hi = paired_interval(truth_score, truth[a], truth[b], idx)
            c_lo, c_hi = paired_interval(score, errors[a], errors[b], idx)
            if (t_lo > 0 and c_hi < 0) or (t_hi < 0 and c_lo > 0):
                contradictions.append(f"{a} vs {b}: truth [{t_lo:+.1f}, {t_hi:+.1f}], "
                                      f"consensus [{c_lo:+.1f}, {c_hi:+.1f}]")
    ladder = [m for m in LADDER if m in methods]
    in_order = {column: all(table.set_index("method").loc[a, column] > table.set_index("method").loc[b, column]
                            for a, b in zip(ladder, ladder[1:])) for column in ("truth", "consensus")}
    print(table.sort_values("truth", ascending=False).to_string(index=False, float_format="%.1f"))
    print(f"ladder {' > '.join(ladder)}: in order by the truth {in_order['truth']}, by the consensus "
          f"{in_order['consensus']}")
    print(f"{len(names)} pairs; Kendall tau {tau:.3f}; Spearman rho per pair {rho:.3f} ({len(both)} run-pairs); "
          f"contradictions: {len(contradictions)}")
    for line in contradictions:
        print("  " + line)
    if args.csv:
        table.insert(0, "set", args.set)
        table.assign(n_pairs=len(names), tau=tau, rho=rho, contradictions=len(contradictions),
                     ladder_in_order=in_order["consensus"]).to_csv(args.csv, index=False)


if __name__ == "__main__":
    main()
