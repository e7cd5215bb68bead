"""Benchmark datasets: each yields ``Pair`` objects (image paths and ground truth), never images.

Which dataset serves which benchmark is said once, in the benchmark registry (benchmarks/).
"""

from e3cm_bench.datasets.base import DatasetError, Pair, PairList
from e3cm_bench.datasets.hpatches import LARGE_SEQUENCES, HPatches
from e3cm_bench.datasets.megadepth import MegaDepth1500
from e3cm_bench.datasets.yfcc import YFCC100M

__all__ = ["LARGE_SEQUENCES", "DatasetError", "HPatches", "MegaDepth1500", "Pair", "PairList", "YFCC100M"]
