"""What --pair-timeout's stoppable child costs per pair, and what the plugin import probe costs.

Prints measured figures (docs/robustness.md quotes them): the time of one pair through a
matcher that does nothing, in this process and through the StoppableWorker's child (the
images sent over a socket, the matches sent back), for images of HPatches' size; the fork of
a fresh child; and the forked probe of one plugin import (plugin_import.probe).

    python scripts/measure/pair_timeout_overhead.py [--pairs 200] [--side 1000]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from e3cm_bench.matchers import plugin_import
from e3cm_bench.matchers.guards import StoppableWorker
from e3cm_bench.ground.matches import Matches
from e3cm_bench.pipeline.pair import checked_match, match_worker


class Nothing:
    """Returns 2000 matches without looking at the images: only the overhead is timed."""

    name = "nothing"

    def __init__(self) -> None:
        rng = np.random.default_rng(0)
        self.points = (rng.random((2000, 2)) * 500).astype(np.float32)

    def match(self, image0, image1) -> Matches:
        return Matches(self.points, self.points.copy(), np.ones(len(self.points), np.float32))


def per_call(call, pairs: int) -> float:
    times = []
    for _ in range(pairs):
        t = time.perf_counter()
        call()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=200)
    parser.add_argument("--side", type=int, default=1000, help="longer side of the two images (HPatches: ~1000)")
    args = parser.parse_args()
    rng = np.random.default_rng(1)
    shape = (args.side * 3 // 4, args.side, 3)
    image0, image1 = (rng.integers(0, 255, shape, dtype=np.uint8) for _ in range(2))
    matcher = Nothing()
    here = per_call(lambda: checked_match(matcher, image0, image1), args.pairs)
    worker = match_worker(matcher)
    worker.start()
    child = per_call(lambda: worker.call((image0, image1, 0), 60), args.pairs)
    worker.close()
    forks = []
    for _ in range(20):
        fresh = StoppableWorker(lambda: 0, "fork")
        t = time.perf_counter()
        fresh.call((), 60)
        forks.append(time.perf_counter() - t)
        fresh.close()
    probes = []
    for _ in range(20):
        t = time.perf_counter()
        plugin_import.probe(lambda: __import__("json"), "json", 60)
        probes.append(time.perf_counter() - t)
    print(f"images {shape[1]}x{shape[0]} x2, 2000 matches, median of {args.pairs} pairs:")
    print(f"  in this process:        {here * 1e3:8.2f} ms per pair")
    print(f"  in the stoppable child: {child * 1e3:8.2f} ms per pair (+{(child - here) * 1e3:.2f} ms)")
    print(f"  a fresh child (fork + first answer): {statistics.median(forks) * 1e3:.1f} ms (median of 20)")
    print(f"  the forked probe of an import already loaded: {statistics.median(probes) * 1e3:.1f} ms (median of 20)")


if __name__ == "__main__":
    main()
