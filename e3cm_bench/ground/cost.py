"""What matching one pair costs: wall time and the peak memory of the process that matched it.

The peak is Linux's high-water mark of the resident set (VmHWM), reset before each pair by
writing 5 to /proc/self/clear_refs, so that one pair's peak is not the run's highest so far:
it counts everything resident (interpreter, libraries, weights, caches), which is what a user
sizing a machine needs. Where the mark cannot be reset (another OS, a kernel that refuses),
the process's lifetime peak (getrusage) stands in and `PEAK_KIND` says so. On a CUDA device
the allocator's peak of the pair is recorded beside it."""

from __future__ import annotations

import contextlib
import resource
import sys
import time
from dataclasses import dataclass

_CLEAR_REFS = "/proc/self/clear_refs"
_STATUS = "/proc/self/status"


def _reset_high_water_mark() -> bool:
    try:
        with open(_CLEAR_REFS, "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _high_water_mb() -> float | None:
    try:
        with open(_STATUS) as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    return None


def lifetime_peak_mb() -> float:
    """The process's peak resident set since it started (MiB)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024.0 * 1024.0) if sys.platform == "darwin" else peak / 1024.0


@dataclass
class PairCost:
    """Filled when the `measured` block ends: seconds, peak_mb (host), gpu_peak_mb (None off CUDA),
    and whether the peak is this block's own (True) or the process's lifetime peak (False)."""

    seconds: float = float("nan")
    peak_mb: float = float("nan")
    gpu_peak_mb: float | None = None
    own_peak: bool = False

    def attrs(self) -> dict:
        """As the match cache stores them beside a pair's matches (match_seconds is the pair's own)."""
        out = {"match_peak_mb": float(self.peak_mb), "match_peak_own": bool(self.own_peak)}
        if self.gpu_peak_mb is not None:
            out["match_gpu_peak_mb"] = float(self.gpu_peak_mb)
        return out


def _cuda_in_use() -> bool:
    torch = sys.modules.get("torch")  # never imported here for a matcher that does not use it
    return torch is not None and torch.cuda.is_available() and torch.cuda.is_initialized()


@contextlib.contextmanager
def measured():
    """`with measured() as cost:` the block's wall time and peak memory, in `cost` after it."""
    cost = PairCost()
    own = _reset_high_water_mark()
    cuda = _cuda_in_use()
    if cuda:
        import torch

        torch.cuda.reset_peak_memory_stats()
    t = time.perf_counter()
    try:
        yield cost
    finally:
        cost.seconds = time.perf_counter() - t
        mark = _high_water_mb() if own else None
        cost.own_peak = mark is not None
        cost.peak_mb = mark if mark is not None else lifetime_peak_mb()
        if cuda or _cuda_in_use():
            import torch

            cost.gpu_peak_mb = torch.cuda.max_memory_allocated() / (1024.0 * 1024.0)
