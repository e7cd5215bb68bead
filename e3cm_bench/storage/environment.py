"""Where a run's numbers were made, as `check` compares it with a baseline's: the packages and
CPU settings its config.yaml records (RunConfig.versions and .environment), as an ordered
``name=value`` string a baseline row holds, read back, and compared setting by setting.
"""

from __future__ import annotations

from collections.abc import Mapping

from e3cm_bench.storage import RunConfig

# What the environment string records, in its order: the packages the numbers depend on, then
# the CPU settings (config.yaml's environment; the ISA variables only where they were set).
ENVIRONMENT_PACKAGES = ("python", "torch", "torchvision", "numpy", "opencv-python-headless")
ISA_KEYS = ("ONEDNN_MAX_CPU_ISA", "ATEN_CPU_CAPABILITY")


def run_environment_items(config: RunConfig | Mapping) -> dict[str, str]:
    """What a run's numbers depend on, from its config.yaml, as ordered ``name -> value`` strings.

    Packages (ENVIRONMENT_PACKAGES, from ``versions``), then ``cpu`` (torch's CPU capability),
    the ISA variables that were set, ``threads`` (from ``environment``). A run written before
    ``environment`` was recorded has only its packages; one without ``versions`` nothing.
    """
    if not isinstance(config, RunConfig):
        config = RunConfig.from_dict(dict(config))
    versions, environment = config.versions, config.environment
    # torch's version with its build tag (environment.torch) where recorded, else the package's
    packages = {**versions, **({"torch": environment["torch"]} if environment.get("torch") else {})}
    items = {name: str(packages[name]) for name in ENVIRONMENT_PACKAGES if packages.get(name) is not None}
    if environment.get("cpu_capability") is not None:
        items["cpu"] = str(environment["cpu_capability"])
    items.update({name: str(environment[name]) for name in ISA_KEYS if environment.get(name)})
    if environment.get("threads") is not None:
        items["threads"] = str(environment["threads"])
    return {name: _clean(value) for name, value in items.items()}


def _clean(value: str) -> str:
    """A value that survives the string's syntax (no separators, no spaces)."""
    return "".join(value.split()).replace(";", ",").replace("=", ":") or "?"


def environment_string(config: RunConfig | Mapping) -> str:
    """E.g. ``python=3.12.3; torch=2.14.1+cu130; ...; cpu=AVX512; threads=2`` (see run_environment_items)."""
    return "; ".join(f"{name}={value}" for name, value in run_environment_items(config).items())


def parse_environment(value) -> dict[str, str]:
    """An environment string back into ``name -> value``; empty for a missing cell, and pieces
    that are no ``name=value`` are ignored (a hand-edited note does not break a check)."""
    if not isinstance(value, str):
        return {}
    items = {}
    for piece in value.split(";"):
        name, sep, item = piece.partition("=")
        if sep and name.strip() and item.strip():
            items[name.strip()] = item.strip()
    return items


def _same_version(before: str, now: str) -> bool:
    """Equal, or equal but for a build tag only one side records (``2.14.1`` vs ``2.14.1+cu130``:
    a package's metadata may lack the tag that torch's own version string has)."""
    if before == now:
        return True
    (b, b_tag), (n, n_tag) = before.partition("+")[::2], now.partition("+")[::2]
    return b == n and not (b_tag and n_tag)


def environment_differences(baseline: dict[str, str], measured: dict[str, str]) -> list[str]:
    """``name before -> now`` for each setting recorded on both sides that differs, packages first.

    A side that records the CPU settings (``cpu``) but no ISA variable had it unset; a side that
    records no CPU settings (a run older than them) is compared on its packages only.
    """
    both_cpu = "cpu" in baseline and "cpu" in measured
    order = [*ENVIRONMENT_PACKAGES, "cpu", *ISA_KEYS, "threads"]
    names = sorted(set(baseline) | set(measured), key=lambda n: (order.index(n) if n in order else len(order), n))
    changes = []
    for name in names:
        before, now = baseline.get(name), measured.get(name)
        if name in ISA_KEYS and both_cpu:
            before, now = before or "unset", now or "unset"
        if before is None or now is None or _same_version(before, now):
            continue
        changes.append(f"{name} {before} -> {now}")
    return changes
