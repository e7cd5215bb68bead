"""How the ground-truth-free score (sfm/consensus.py) agrees with the ground truth, on finished sfm
runs of several matchers over one set (each run's own reconstruction, models under RUN/sfm/models).

    python scripts/validate/consensus_vs_truth.py RUN [RUN ...] [--csv OUT.csv] [--exclude NAME ...]

For every run: its ground-truth auc@10 over the pairs (from its per_pair.csv, the first mapper
seed), and its consensus score against the other runs' reconstructions of the same pairs. Prints
both rankings, Kendall's tau between the two scores (scipy.stats), Spearman's rho per pair between
the ground-truth error and the consensus error (pooled over matchers), and every pair of matchers
that both paired intervals separate in opposite directions.
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


def paired_interval(a: np.ndarray, b: np.ndarray, idx: np.ndarray) -> tuple[float, float]:
    """Interval of score(a) - score(b) over the resamples idx (rows of pair indices)."""
    return percentile_interval(np.array([consensus.score(a[r]) - consensus.score(b[r]) for r in idx]))


def main() -> None:
    from scipy import stats

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--csv", type=Path)
    args = parser.parse_args()
    names, poses, truth = None, {}, {}
    for run in args.runs:
        found = run_poses(run)
        if names is not None and found.names != names:
            raise SystemExit(f"{run}: its pairs differ from {args.runs[0]}'s")
        names = found.names
        per_pair = pd.read_csv(RunFolder(run).per_pair_path).set_index("pair").loc[names]
        poses[run.name], truth[run.name] = found.poses, per_pair["err_pose"].to_numpy(np.float64)
    errors = consensus.consensus_errors(poses)
    table = pd.DataFrame({"method": list(poses),
                          "truth_auc10": [consensus.score(truth[m]) for m in poses],
                          "consensus": [consensus.score(errors[m]) for m in poses]})
    tau = stats.kendalltau(table["truth_auc10"], table["consensus"]).statistic
    both = np.concatenate([np.stack([truth[m], errors[m]], 1) for m in poses])
    both = both[~np.isnan(both).any(axis=1)]
    rho = stats.spearmanr(both[:, 0], both[:, 1]).statistic
    idx = resample_indices(len(names), 1000, 0)
    contradictions = []
    methods = list(poses)
    for i, a in enumerate(methods):
        for b in methods[i + 1:]:
            t_lo, t_hi = paired_interval(truth[a], truth[b], idx)
            c_lo, c_hi = paired_interval(errors[a], errors[b], idx)
            if (t_lo > 0 and c_hi < 0) or (t_hi < 0 and c_lo > 0):
                contradictions.append(f"{a} vs {b}: truth [{t_lo:+.1f}, {t_hi:+.1f}], consensus [{c_lo:+.1f}, {c_hi:+.1f}]")
    print(table.sort_values("truth_auc10", ascending=False).to_string(index=False, float_format="%.1f"))
    print(f"Kendall tau {tau:.3f}; Spearman rho per pair {rho:.3f} ({len(both)} matcher-pairs); "
          f"contradictions: {len(contradictions)}")
    for line in contradictions:
        print("  " + line)
    if args.csv:
        table.assign(tau=tau, rho=rho, contradictions=len(contradictions)).to_csv(args.csv, index=False)


if __name__ == "__main__":
    main()
