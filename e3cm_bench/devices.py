"""Where a model runs: checking a --device, and telling an allocator's failure from a bug."""

from __future__ import annotations


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
    """Bytes of host memory available for new allocations (Linux MemAvailable); None where it cannot be read."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None
