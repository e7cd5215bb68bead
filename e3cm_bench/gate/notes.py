"""What `check` says beside its verdict, never a failure: where a run's environment (packages,
CPU settings) or its protocol (storage/fingerprint.py) differs from its baseline row's."""

from __future__ import annotations

import json
from pathlib import Path

from e3cm_bench.gate.check import ENVIRONMENT_COLUMN, PROTOCOL_COLUMN, read_baseline
from e3cm_bench.reporting.runs import Run
from e3cm_bench.storage.environment import environment_differences, parse_environment, run_environment_items
from e3cm_bench.storage.fingerprint import protocol_items, protocol_notes


def environment_notes(runs: list[Run], baseline_path: Path) -> list[str]:
    """One line per distinct difference between the runs' environments and their baseline rows'.

    A difference shared by every run compared is one line; one that only some runs have names them.
    Runs without a baseline row, and rows without an environment, are not compared.
    """
    baseline = read_baseline(baseline_path)
    if ENVIRONMENT_COLUMN not in baseline.columns:
        return []
    rows = {(str(r["benchmark"]), str(r["method"])): parse_environment(r[ENVIRONMENT_COLUMN])
            for _, r in baseline.iterrows()}
    groups: dict[tuple[str, ...], list[str]] = {}
    compared = 0
    for run in runs:
        key = (run.benchmark.name, run.label)
        if key not in rows or not rows[key]:
            continue
        compared += 1
        changes = environment_differences(rows[key], run_environment_items(run.run_config))
        if changes:
            groups.setdefault(tuple(changes), []).append(f"{run.label} on {run.benchmark.name}")
    notes = []
    for changes, names in groups.items():
        line = f"environment differs from the baseline's: {', '.join(changes)}"
        notes.append(line if len(names) == compared else f"{line} ({', '.join(names)})")
    return notes


def protocol_check_notes(runs: list[Run], baseline_path: Path) -> list[str]:
    """One line per run scored under another protocol than its baseline row (fingerprints
    differ): what differs. Rows written before the protocol was recorded are not compared."""
    baseline = read_baseline(baseline_path)
    if PROTOCOL_COLUMN not in baseline.columns:
        return []
    recorded = {(str(r["benchmark"]), str(r["method"])): r[PROTOCOL_COLUMN] for _, r in baseline.iterrows()}
    notes = []
    for run in runs:
        cell = recorded.get((run.benchmark.name, run.label))
        if not isinstance(cell, str) or not cell.strip():
            continue
        notes += protocol_notes([(f"baseline of {run.label} on {run.benchmark.name}", json.loads(cell)),
                                 (str(run.dir), protocol_items(run.run_config))])
    return notes
