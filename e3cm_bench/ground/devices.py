"""Where a model runs: checking a --device, telling an allocator's failure from a bug, the
precision a device computes natively, and glibc keeping freed memory for the next pass."""

from __future__ import annotations

import ctypes
import functools
import os
import platform


def check_device(device: str) -> str:
    """The device if torch has it here; else a one-line ValueError naming what is available."""
    import torch

    available = ["cpu"] + [f"cuda:{i}" for i in range(torch.cuda.device_count())]
    if getattr(torch.backends, "mps", None) is not None and torch.backends.mps.is_available():
        available.append("mps")
    try:
        kind = torch.device(device).type
    except (RuntimeError, ValueError):
        raise ValueError(f"--device {device}: not a device; use cpu, cuda, cuda:N or mps "
                         f"(available here: {', '.join(available)})") from None
    index = torch.device(device).index
    if kind == "cuda" and (not torch.cuda.is_available() or (index or 0) >= torch.cuda.device_count()):
        raise ValueError(f"--device {device}: no such CUDA GPU here (available: {', '.join(available)})")
    if kind == "mps" and "mps" not in available:
        raise ValueError(f"--device {device}: Apple's MPS is not available here (available: {', '.join(available)})")
    return device


def is_out_of_memory(error: BaseException) -> bool:
    """torch's allocator failures: CUDA's OutOfMemoryError, or the CPU allocator's RuntimeError."""
    text = str(error).lower()
    return type(error).__name__ == "OutOfMemoryError" or (
        isinstance(error, RuntimeError) and ("out of memory" in text or "can't allocate memory" in text
                                             or "not enough memory" in text))


def available_host_memory() -> int | None:
    """Bytes of host memory available for new allocations: Linux's MemAvailable, plus what this
    process's malloc holds free for reuse where keep_freed_memory keeps it; None where
    MemAvailable cannot be read."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024 + kept_free_bytes()
    except OSError:
        pass
    return None


# How many times slower than fp32 a bf16 pass is where the CPU lacks bf16 instructions and
# oneDNN emulates them: the warning quotes it, so the user sees what --precision bf16 costs
# there. The two timings it is the ratio of: docs/speed.md, "bf16: effect on the results".
EMULATED_BF16_SLOWDOWN = 111.5 / 21.2


def native_bf16(device: str) -> bool:
    """Whether `device` computes bf16 natively: a CUDA GPU torch says supports it, or a CPU
    with AVX-512 BF16 or AMX (the flags oneDNN's bf16 kernels need)."""
    import torch

    kind = torch.device(device).type
    if kind == "cuda":
        return bool(torch.cuda.is_available() and torch.cuda.is_bf16_supported())
    if kind != "cpu":
        return False
    from e3cm_bench.ground.machine import BF16_FLAGS, cpu_info

    flags = cpu_info()[1] or set()
    return any(flag in flags for flag in BF16_FLAGS)


def resolve_precision(precision: str, device: str) -> tuple[str, str | None]:
    """--precision as it will run on `device`, and a one-line warning where it will be slow:
    auto picks bf16 where the device computes it natively (fp16 on a GPU without bf16), else
    fp32; bf16 asked for on a CPU without native bf16 runs, emulated, with a warning."""
    import torch

    kind = torch.device(device).type
    if precision == "auto":
        if native_bf16(device):
            return "bf16", None
        return ("fp16" if kind in ("cuda", "mps") else "fp32"), None
    if precision == "bf16" and kind == "cpu" and not native_bf16(device):
        return "bf16", (
            f"this CPU has no native bf16 (AVX-512 BF16 or AMX): bf16 will be emulated, measured "
            f"{EMULATED_BF16_SLOWDOWN:.1f}x slower than fp32 on such a CPU; --precision fp32 or auto is faster here"
        )
    return precision, None


# glibc's mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_MAX, _M_ARENA_MAX = -1, -4, -8
ALLOCATOR_VARIABLE = "E3CM_BENCH_ALLOCATOR"
_allocator: str | None = None  # what keep_freed_memory found or made; None until it is called
_kept = False  # whether glibc now keeps freed memory


class _MallInfo2(ctypes.Structure):  # glibc's struct mallinfo2 (2.33 and later)
    _fields_ = [
        (name, ctypes.c_size_t)
        for name in (
            "arena",
            "ordblks",
            "smblks",
            "hblks",
            "hblkhd",
            "usmblks",
            "fsmblks",
            "uordblks",
            "fordblks",
            "keepcost",
        )
    ]


@functools.lru_cache(maxsize=1)
def _glibc() -> ctypes.CDLL | None:
    """The C library when it is glibc (the one this process runs on), else None."""
    if platform.libc_ver()[0] != "glibc":
        return None
    try:
        return ctypes.CDLL("libc.so.6")
    except OSError:
        return None


def keep_freed_memory() -> str:
    """Have glibc's malloc keep freed memory for the next allocation instead of giving it back to
    the system; returns what the process's allocator does now (config.yaml's
    ``environment.allocator``).

    torch's CPU tensors come from malloc, and glibc serves each block above its mmap threshold
    (at most 32 MiB: a feature map, a convolution's output) with a fresh mmap and unmaps it
    when freed: the next pass touches new pages, and the kernel zeroes each one on a page
    fault. On this project's machine that was up to a quarter of a VGG19 pass
    (docs/speed.md; its removed A/B script is in the git history). With mmap off (M_MMAP_MAX 0) and the heap
    never trimmed, the pages of one pass serve the next. The values computed are the same (a
    test compares the matches); the process keeps its peak memory until it exits.
    Idempotent; E3CM_BENCH_ALLOCATOR=system leaves the allocator as it is; a C library other
    than glibc is left as it is.
    """
    global _allocator, _kept
    if _allocator is not None:
        return _allocator
    if os.environ.get(ALLOCATOR_VARIABLE, "").strip().lower() == "system":
        _allocator = f"system ({ALLOCATOR_VARIABLE}=system)"
    elif platform.libc_ver()[0] != "glibc":
        _allocator = f"system ({platform.libc_ver()[0] or 'not glibc'})"
    else:
        libc = _glibc()
        try:
            # One arena: each thread that allocates (torch's intra-op threads, the decoding thread)
            # would otherwise get an arena of its own, and each would keep its own freed memory:
            # e3cm-plus on 1.6x-enlarged HPatches pairs peaked at 3.7 GB with them, 3.3 GB with one,
            # at the same speed (scripts/measure/e3cm_memory.py, docs/speed.md "Memory").
            _kept = (libc is not None and libc.mallopt(_M_MMAP_MAX, 0) == 1
                     and libc.mallopt(_M_TRIM_THRESHOLD, 2**31 - 1) == 1 and libc.mallopt(_M_ARENA_MAX, 1) == 1)
        except AttributeError:
            _kept = False
        _allocator = (
            "glibc, freed memory kept (M_MMAP_MAX=0, no trim, one arena)" if _kept else "system (mallopt failed)"
        )
    return _allocator


def allocator() -> str:
    """What keep_freed_memory made of this process's allocator ("system" if it was not called)."""
    return _allocator or "system"


def kept_free_bytes() -> int:
    """Bytes this process's malloc holds free for reuse (glibc's mallinfo2 fordblks) where
    keep_freed_memory keeps them, else 0: memory the system no longer counts as available
    although the next tensors take it first."""
    mallinfo2 = getattr(_glibc(), "mallinfo2", None) if _kept else None  # glibc 2.33 and later
    if mallinfo2 is None:
        return 0
    mallinfo2.restype = _MallInfo2
    return int(mallinfo2().fordblks)
