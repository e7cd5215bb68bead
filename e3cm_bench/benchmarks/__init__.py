"""The benchmark registry: name -> Benchmark.

Adding a benchmark: one file defining its `Benchmark` (usually a `HomographyBenchmark` or
`PoseBenchmark` with its own dataset class), plus one `register(...)` line here.
"""

from __future__ import annotations

from .base import Benchmark, EvalSettings
from .homography import HPATCHES, HomographyBenchmark
from .pose import MEGADEPTH, YFCC, PoseBenchmark

BENCHMARKS: dict[str, Benchmark] = {}


def register(benchmark: Benchmark) -> Benchmark:
    BENCHMARKS[benchmark.name] = benchmark
    return benchmark


def get_benchmark(name: str | Benchmark) -> Benchmark:
    if isinstance(name, Benchmark):
        return name
    if name not in BENCHMARKS:
        raise ValueError(f"unknown benchmark {name!r}; choose one of {', '.join(BENCHMARKS)}")
    return BENCHMARKS[name]


register(HPATCHES)
register(MEGADEPTH)
register(YFCC)

__all__ = ["BENCHMARKS", "Benchmark", "EvalSettings", "HomographyBenchmark", "PoseBenchmark", "get_benchmark", "register"]
