"""The address space a run still needs under a ulimit -v: checked before and after matching, so
that a too tight limit ends in one line instead of a library's crash."""

from __future__ import annotations

import re
import resource

# OpenCV's wheel brings its own OpenBLAS, which reserves its work buffer with mmap at its first
# use (the evaluation's first cv2.findHomography); where an address-space limit (ulimit -v)
# makes that mmap fail, it calls a null pointer: a segmentation fault, no message, after the
# matching. Measured: that first call needs between 128 and 160 MiB of address space; the rest
# leaves room for a thread's malloc arena (64 MiB) and stacks.
ADDRESS_SPACE_NEEDED_MB = 320


def address_space_left_mb() -> float | None:
    """MiB of address space this process may still map under its RLIMIT_AS (None: no limit)."""
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft == resource.RLIM_INFINITY:
        return None
    try:
        size_kb = int(re.search(r"VmSize:\s+(\d+)", open("/proc/self/status").read()).group(1))
    except (OSError, AttributeError):
        return None
    return (soft - size_kb * 1024) / 2**20


def check_address_space(when: str, pairs: int) -> None:
    """A one-line ValueError where the address-space limit leaves too little for the libraries
    still to run (ADDRESS_SPACE_NEEDED_MB), instead of their crash."""
    left = address_space_left_mb()
    if left is None or left >= ADDRESS_SPACE_NEEDED_MB:
        return
    soft = resource.getrlimit(resource.RLIMIT_AS)[0]
    kept = f"; the {pairs} pair(s) matched are kept and the same command resumes" if pairs else "; nothing was matched"
    raise ValueError(
        f"{when}: the address-space limit (ulimit -v {soft // 1024}) leaves {max(left, 0):.0f} MiB in this "
        f"process, and matching and evaluating need about {ADDRESS_SPACE_NEEDED_MB} MiB more (OpenCV's BLAS "
        f"crashes without them): raise the limit, e.g. ulimit -v unlimited{kept}"
    )
