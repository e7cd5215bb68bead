"""Benchmark datasets: each yields ``Pair`` objects (image paths and ground truth), never images."""

from e3cm_bench.datasets.base import DatasetError, Pair, PairList
from e3cm_bench.datasets.hpatches import LARGE_SEQUENCES, HPatches
from e3cm_bench.datasets.megadepth import MegaDepth1500
from e3cm_bench.datasets.yfcc import YFCC100M

DATASETS = {
    "hpatches": HPatches,
    "megadepth": MegaDepth1500,
    "yfcc": YFCC100M,
}
BENCHMARKS = tuple(DATASETS)  # "hpatches", "megadepth", "yfcc"

__all__ = [
    "BENCHMARKS",
    "DATASETS",
    "LARGE_SEQUENCES",
    "DatasetError",
    "HPatches",
    "MegaDepth1500",
    "Pair",
    "PairList",
    "YFCC100M",
]
