"""The machine and libraries a result was made with: package versions, the CPU's model and
instruction sets, and what torch dispatches to (config.yaml's ``versions`` and ``environment``:
oneDNN picks other kernels on other instruction sets, and those round differently)."""

from __future__ import annotations

import os
import platform
from importlib import metadata
from pathlib import Path

PACKAGES = tuple("e3cm-bench torch torchvision numpy opencv-python-headless h5py pandas poselib pycolmap".split())
# Variables that choose the CPU kernels (oneDNN, ATen), and the CPU flags the defaults pick them by.
ISA_VARIABLES = ("ONEDNN_MAX_CPU_ISA", "ATEN_CPU_CAPABILITY")
CPU_FLAGS = ("avx512_bf16", "amx_bf16", "avx512f", "avx2")
# The flags of those with which a CPU computes bf16 natively (oneDNN's bf16 kernels need one).
BF16_FLAGS = ("avx512_bf16", "amx_bf16")


def package_versions() -> dict[str, str]:
    versions = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return versions


def cpu_info() -> tuple[str | None, set[str] | None]:
    """The CPU's model name and flags from /proc/cpuinfo (first processor); (None, None) where absent."""
    try:
        text = Path("/proc/cpuinfo").read_text(errors="replace")
    except OSError:
        return None, None
    model, flags = None, None
    for line in text.splitlines():
        key, _, value = line.partition(":")
        key = key.strip()
        if model is None and key in ("model name", "Processor", "cpu model"):
            model = value.strip() or None
        elif flags is None and key in ("flags", "Features"):
            flags = set(value.split())
        if model is not None and flags is not None:
            break
    return model, flags


def cpu_isa() -> str:
    """The CPU's instruction sets that decide its speed here, as "avx512_bf16+avx512f+avx2"
    ("unknown" where /proc/cpuinfo is absent): what the speed tables print beside each figure."""
    _, flags = cpu_info()
    return "+".join(f for f in CPU_FLAGS if f in (flags or ())) or "unknown"


def run_environment() -> dict:
    """What a run's numbers depend on beyond package versions (config.yaml's ``environment``).

    torch's version string with its build tag, the CPU capability torch dispatches to
    (``torch.backends.cpu.get_cpu_capability()``: AVX512, AVX2, DEFAULT ...), the environment
    variables that change it (recorded only when set), torch's thread count, the CPU model and
    whether it has each of CPU_FLAGS (null where /proc/cpuinfo is absent).
    oneDNN picks other convolution kernels on other instruction sets, and those round differently.
    """
    import torch  # lazily: this module is imported by commands that never need torch

    capability = str(torch.backends.cpu.get_cpu_capability())
    model, flags = cpu_info()
    # torch's own version string names its build (2.14.1+cu130, 2.14.1+cpu), which the
    # package metadata in `versions` may not.
    environment = {"torch": str(torch.__version__), "cpu_capability": capability}
    environment.update({name: os.environ[name] for name in ISA_VARIABLES if os.environ.get(name)})
    environment["threads"] = int(torch.get_num_threads())
    environment["cpu_model"] = model or platform.processor() or platform.machine() or "unknown"
    environment["cpu_flags"] = None if flags is None else {flag: flag in flags for flag in CPU_FLAGS}
    return environment
