"""Add bootstrap intervals to run folders written before summary.csv carried them, and rewrite
the tables made from them (how results/sample/ got its intervals without rerunning anything).

    python scripts/add_intervals.py results/sample/table1_hpatches results/sample/table2_kitti ...

Each TABLE_DIR holds run folders (config.yaml, summary.csv, per_pair.csv) and the table.csv /
table.md made from them. For each run, the intervals are recomputed from its per_pair.csv with
its recorded evaluation settings (intervals.recompute, which refuses a run whose pairs do not
reproduce its summary); every point value of summary.csv is kept as written, and checked to be
so. The table is then rewritten in its own row order, keeping the columns it had (a table
made with --no-compare stays without differences); its plots are left as they are.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd

from e3cm_bench import intervals

from e3cm_bench.reporting import tables as report
from e3cm_bench.files import write_csv


def upgrade_run(run_dir: Path) -> None:
    run = report.load_run(run_dir)
    before = pd.read_csv(run_dir / "summary.csv")
    point = {k: v for k, v in run.summary.items() if not intervals.is_interval_key(k)}
    ev = report.eval_settings_of(run)
    added = intervals.recompute(run.benchmark, point, run.per_pair, ev) if ev is not None else None
    if added is None:
        raise SystemExit(f"{run_dir}: its per_pair.csv does not reproduce its summary.csv; no interval added")
    write_csv(pd.DataFrame([{**point, **added}]), run_dir / "summary.csv")
    after = pd.read_csv(run_dir / "summary.csv")
    kept = [c for c in before.columns if not intervals.is_interval_key(c)]
    if not after[kept].equals(before[kept]):
        raise SystemExit(f"{run_dir}: a point value changed on rewrite")


def rewrite_table(table_dir: Path) -> None:
    old = pd.read_csv(table_dir / "table.csv")
    runs = {}
    for config in sorted(table_dir.glob("*/config.yaml")):
        run = report.load_run(config.parent)
        runs[run.label] = config.parent
    order = [m for m in old.loc[old["source"] == "measured", "method"]]
    missing = [m for m in order if m.removesuffix(" (non-standard)") not in runs]
    if missing:
        raise SystemExit(f"{table_dir}: no run folder for {', '.join(missing)}")
    loaded = [report.load_run(runs[m.removesuffix(" (non-standard)")]) for m in order]
    benchmark = loaded[0].benchmark
    reference = report.paper_reference(benchmark) if (old["source"] == "paper").any() else None
    table = report.paper_table(loaded, benchmark, reference)
    if not any(c.startswith("d_") for c in old.columns):
        table = report.without_comparison(table)
    for column in old.columns:
        if column not in table.columns:
            raise SystemExit(f"{table_dir}: the new table lacks column {column}")
        if not table[column].equals(old[column]) and not (table[column].astype(str) == old[column].astype(str)).all():
            kept = pd.to_numeric(table[column], errors="coerce").round(6).equals(pd.to_numeric(old[column], errors="coerce").round(6))
            if not kept:
                raise SystemExit(f"{table_dir}: column {column} changed")
    report.write_paper_table(table, table_dir / "table")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("tables", nargs="+", type=Path)
    args = parser.parse_args(argv)
    for table_dir in args.tables:
        for config in sorted(table_dir.glob("*/config.yaml")):
            upgrade_run(config.parent)
        rewrite_table(table_dir)
        print(f"{table_dir}: intervals added, table rewritten")
    return 0


if __name__ == "__main__":
    sys.exit(main())
