"""What matching one pair costs: wall time and the peak memory of the process that matched it.

The peak is Linux's high-water mark of the resident set (VmHWM), reset before each pair by
writing 5 to /proc/self/clear_refs, so that one pair's peak is not the run's highest so far:
it counts everything resident (interpreter, libraries, weights, caches), which is what a user
sizing a machine needs. Where the mark cannot be reset (another OS, a kernel that refuses),
the process's lifetime peak (getrusage) stands in and `PEAK_KIND` says so. On a CUDA device
the allocator's peak of the pair is recorded beside it.

Where several methods are matched in one process (demo, reproduce), a pair's peak counts every
method's weights and maps: it is the process's, not the method's, and is recorded as shared
(pipeline/stage.py), never as one method's own.

A time is only as good as the machine was idle: a small network under another process's load
ran 0.4 to 1.7 s per image instead of 0.03 s (OpenMP threads oversubscribed). `machine_load`
records the load beside a stage's time; `under_load` says when it was too high to trust."""

from __future__ import annotations

import contextlib
import os
import resource
import sys
import time
from collections.abc import Mapping
from dataclasses import dataclass

# Set on a pair matched in a process that held other methods too (pipeline/stage.py): its peaks
# are the process's, shared by the methods, not this method's own (evaluate.pair_cost: blank).
SHARED_PEAK = "match_peak_shared"
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


# A cost taken with more than this share of the usable cores busy before the stage began, or more
# runnable threads than cores at its end (its own included), is flagged as taken under load.
BUSY_AT_START = 0.5


def usable_cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        return os.cpu_count() or 1


def _load_average() -> float | None:
    try:
        return round(os.getloadavg()[0], 2)
    except (AttributeError, OSError):
        return None


@contextlib.contextmanager
def machine_load():
    """`with machine_load() as load:` the machine's load around the block, in the dict `load`
    after it: the 1-minute load average at its start and its end, the usable cores, and this
    process's CPU seconds (all its threads) beside the block's wall seconds."""
    load: dict = {}
    start, cpu, wall = _load_average(), time.process_time(), time.perf_counter()
    try:
        yield load
    finally:
        load.update(load_start=start, load_end=_load_average(), cpus=usable_cpus(),
                    cpu_seconds=round(time.process_time() - cpu, 3), wall_seconds=round(time.perf_counter() - wall, 3))


def worse_load(before: Mapping | None, now: Mapping) -> dict:
    """A resumed run's load: the higher load averages of its stages, their CPU and wall seconds added."""
    if not before:
        return dict(now)
    out = dict(now)
    for key in ("load_start", "load_end"):
        values = [v for v in (before.get(key), now.get(key)) if v is not None]
        out[key] = max(values) if values else None
    for key in ("cpu_seconds", "wall_seconds"):
        out[key] = round(float(before.get(key) or 0) + float(now.get(key) or 0), 3)
    return out


def under_load(load: Mapping | None) -> str:
    """'' for a cost measured on a machine idle enough (or with no load recorded: a run made
    before it was), else a line saying how loaded the machine was (`BUSY_AT_START`)."""
    if not isinstance(load, Mapping):
        return ""
    start, end, cpus = load.get("load_start"), load.get("load_end"), load.get("cpus") or 1
    if not ((start is not None and start > BUSY_AT_START * cpus) or (end is not None and end > cpus)):
        return ""
    return (f"cost measured under load: load average {start} at the start, {end} at the end, on {cpus} cores; "
            f"CPU {float(load.get('cpu_seconds') or 0):.0f} s in {float(load.get('wall_seconds') or 0):.0f} s")
