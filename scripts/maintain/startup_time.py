"""How long the command line takes to answer before it does any work: `e3cm-bench --help`,
`e3cm-bench hpatches --help`, `--version` and a mistyped command, each run N times in a fresh
process; prints the median and the range of the wall time, the median CPU time (user +
system: about the wall time of an idle machine), and which heavy libraries the import of the
command line loads. Target: under 1.0 s each on an idle machine, no torch.

    python scripts/maintain/startup_time.py [--runs 7] [--command e3cm-bench]

The figures depend on the machine and its load (run it idle: `uptime` is printed with them);
docs/cli.md quotes a measurement.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

COMMANDS = (["--help"], ["hpatches", "--help"], ["--version"], ["hpatchez"])
HEAVY = ("torch", "scipy", "pandas", "matplotlib", "cv2", "h5py")


def timed(command: list[str]) -> tuple[float, float, int]:
    """Wall seconds, CPU seconds (user + system, the child's) and exit status of one run. On a
    loaded machine the wall time waits for a core; the CPU time is about what an idle one takes
    (the start is one thread)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    done = subprocess.run(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=False)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), done.returncode


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=7, help="runs of each command (the median is printed)")
    parser.add_argument("--command", default=shutil.which("e3cm-bench") or "", help="the installed entry point")
    args = parser.parse_args()
    entry = [args.command] if args.command else [sys.executable, "-m", "e3cm_bench"]
    with open("/proc/loadavg") if os.path.exists("/proc/loadavg") else open(os.devnull) as f:
        load = f.read().split()[:3]
    print(f"{' '.join(entry)}; {os.cpu_count()} CPUs, load average {' '.join(load) or 'unknown'}; "
          f"median of {args.runs} runs")
    timed(entry + ["--version"])  # a first run warms the file cache, as any second command finds it
    for words in COMMANDS:
        times, cpu, codes = [], [], set()
        for _ in range(args.runs):
            seconds, used, code = timed(entry + words)
            times.append(seconds)
            cpu.append(used)
            codes.add(code)
        print(f"  e3cm-bench {' '.join(words):<18} {statistics.median(times):6.2f} s  "
              f"(min {min(times):.2f}, max {max(times):.2f}); CPU {statistics.median(cpu):.2f} s; "
              f"exit {', '.join(map(str, sorted(codes)))}")
    probe = ("import sys, time; t = time.perf_counter(); import e3cm_bench.cli; "
             "print(round(time.perf_counter() - t, 2), [m for m in %r if m in sys.modules])" % (HEAVY,))
    # From a neutral folder: `python -c` puts the current folder first on sys.path, which would
    # import a checkout found there instead of the installed (or PYTHONPATH's) package.
    seconds, loaded = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True,
                                     cwd=tempfile.gettempdir()).stdout.split(" ", 1)
    print(f"  import e3cm_bench.cli: {seconds} s; heavy libraries it loads: {loaded.strip()}")


if __name__ == "__main__":
    main()
