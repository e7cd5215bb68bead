"""The benchmark registry: name -> Benchmark.

Adding a benchmark is adding one module to this package that defines a module-level
``BENCHMARKS`` tuple (its `Benchmark` objects: usually a `HomographyBenchmark` or a
`PoseBenchmark` with its own dataset class, or a subclass of its own), plus its data source
in datasets/sources.py. Every module here is read once, on first use, so nothing else needs
to name the new one: its command (`e3cm-bench NAME`), `import`, `reproduce` and the report
all come from the registry. `register` adds one from outside the package (the Python API).
"""

from __future__ import annotations

import importlib
import pkgutil

from e3cm_bench.ground.suggest import did_you_mean
from e3cm_bench.benchmarks.base import Benchmark, DatasetOption
from e3cm_bench.benchmarks.eval_settings import EvalSettings
from e3cm_bench.benchmarks.homography import HomographyBenchmark
from e3cm_bench.benchmarks.pose import PoseBenchmark

BENCHMARKS: dict[str, Benchmark] = {}


def register(benchmark: Benchmark) -> Benchmark:
    if not isinstance(benchmark, Benchmark):
        raise TypeError(f"register: expected a Benchmark, got {type(benchmark).__name__}")
    BENCHMARKS[benchmark.name] = benchmark
    return benchmark


# Modules of this package that define no benchmark (the base classes, a run's intervals, what a
# record rebuilds), and the benchmark modules that live with their own package: the multi-view
# benchmark is sfm's (it sits above this package, so it is found by name, as a plugin would be).
NOT_BENCHMARKS = ("base", "intervals", "from_record")
ELSEWHERE = {"sfm": "e3cm_bench.sfm.benchmark"}


def _discover() -> None:
    """Register the BENCHMARKS of every module of this package (and ELSEWHERE's), in the modules'
    name order after the three of the paper (the order `e3cm-bench --help` lists their commands in)."""
    modules = {m.name: f"{__name__}.{m.name}" for m in pkgutil.iter_modules(__path__)
               if not m.name.startswith("_") and m.name not in NOT_BENCHMARKS}
    modules.update(ELSEWHERE)
    names = sorted(modules)
    first = [n for n in ("homography", "pose") if n in names]
    for name in first + [n for n in names if n not in first]:
        module = importlib.import_module(modules[name])
        for benchmark in getattr(module, "BENCHMARKS", ()):
            BENCHMARKS.setdefault(benchmark.name, benchmark)


# Benchmarks that are no command, found by the name their runs record: reconstruct's (a folder
# of one's own images, no ground truth: `e3cm-bench reconstruct`), so that its shards merge and
# its runs export and draw like any run's.
UNLISTED = {"reconstruct": ("e3cm_bench.sfm.own_images", "RECONSTRUCT")}


def get_benchmark(name: str | Benchmark) -> Benchmark:
    if isinstance(name, Benchmark):
        return name
    if name not in BENCHMARKS and name in UNLISTED:
        module, attribute = UNLISTED[name]
        return getattr(importlib.import_module(module), attribute)
    if name not in BENCHMARKS:
        raise ValueError(
            f"unknown benchmark {name!r}{did_you_mean(name, BENCHMARKS)}; choose one of {', '.join(BENCHMARKS)}"
        )
    return BENCHMARKS[name]


_discover()

__all__ = ["BENCHMARKS", "Benchmark", "DatasetOption", "EvalSettings", "HomographyBenchmark", "PoseBenchmark",
           "get_benchmark", "register"]
