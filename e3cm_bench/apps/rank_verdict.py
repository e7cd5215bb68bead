"""The verdict of `e3cm-bench rank`: finished reconstruct runs of several matchers over one folder
-> one row per matcher, ranked by the ground-truth-free score (sfm/consensus.py), with its interval,
the paired verdict against the next row, the cost and the reconstruction's facts -> OUT/verdict.csv.

A matcher whose run failed keeps a row at the bottom with its reason and no score; it gives no pose
to the others' references either.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pandas as pd

from e3cm_bench.sfm import consensus
from e3cm_bench.sfm.verdict import common_poses, run_poses

VERDICT = "verdict.csv"
# The reconstruction's facts each row repeats from its run's summary.csv.
FACTS = ("n_images", "registered_images", "n_models", "largest_model_images", "points", "mean_track_length",
         "mean_reprojection_error")
COST = ("seconds_per_image", "seconds_per_pair", "mapping_seconds", "peak_memory_mb")
COLUMNS = ("rank", "method", "score", "score_lo", "score_hi", "vs_next", "diff_next", "diff_next_lo", "diff_next_hi",
           "n_pairs_scored", *COST, *FACTS,
           "run", "failed")


def run_cost(run: Path) -> dict:
    """The run's cost as its summary.csv holds it: seconds per image (matching and mapping,
    sfm/own_images.run_cost), per pair (matching), the mapping's seconds, the peak memory."""
    from e3cm_bench.storage.folder import RunFolder

    summary = pd.read_csv(RunFolder(run).summary_path).iloc[0]
    return {key: float(summary.get(key, np.nan)) for key in COST}


def run_facts(run: Path) -> dict:
    from e3cm_bench.storage.folder import RunFolder

    summary = pd.read_csv(RunFolder(run).summary_path).iloc[0]
    return {key: summary.get(key, np.nan) for key in FACTS}


def verdict_table(runs: Mapping[str, Path], failed: Mapping[str, str] | None = None,
                  ranking: consensus.Ranking | None = None) -> pd.DataFrame:
    """The ranked rows (COLUMNS) of the finished `runs` (label -> run folder) and, last, the
    `failed` ones (label -> reason)."""
    failed = dict(failed or {})
    found = {}
    for label, run in runs.items():
        try:
            found[label] = run_poses(run)
        except (OSError, ValueError, KeyError) as error:  # a run folder without its models or record
            failed[label] = f"{run}: cannot be read ({error})"
    errors = consensus.consensus_errors(common_poses(found)) if found else {}
    rows = []
    for row in consensus.rank(errors, ranking):
        label = row["method"]
        facts = run_facts(runs[label])
        rows.append({**row, "n_pairs_scored": int(np.count_nonzero(~np.isnan(errors[label]))),
                     **run_cost(runs[label]), **facts, "run": str(runs[label]), "failed": ""})
    for label, reason in failed.items():
        rows.append({"method": label, "failed": reason, "run": str(runs.get(label, ""))})
    return pd.DataFrame(rows).reindex(columns=list(COLUMNS))


def write_verdict(table: pd.DataFrame, out: Path) -> Path:
    from e3cm_bench.ground.files import write_csv

    return write_csv(table, Path(out) / VERDICT)
