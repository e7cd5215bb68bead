"""The protocol fingerprint: a short hash of everything a run's numbers were scored under, so
that two rows made under different protocols are never read as comparable without a word.

What it covers (protocol_items, from the run's config.yaml): every evaluation setting (the
protocol preset, the estimator, its thresholds and the pixels they are in, confidence,
iterations, the RANSAC seed, repeats), the multi-view protocol where the benchmark has one
(evaluation's mapper, seeds, merge, verification, scored model; dataset.protocol in older records:
the same items either way, so the fingerprint did not move with the block), and the versions of the
libraries whose estimators score them (OpenCV, PoseLib, pycolmap). Not covered: what made the
matches (the matcher, its settings and the image size it matched at: the row's method and its
identity say them; an imported run's matches, made elsewhere, are scored under the same
protocol as a native run's and so share its fingerprint), the data (its pairs), and what
decides only the interval beside each number (the RANSAC seeds it holds, interval_seeds, like
the bootstrap's settings: summary.csv says them beside the interval).

`table`, `compare` and `check` print one line naming what differs where fingerprints differ
(protocol_notes); the summary.csv of every run holds its own (column ``fingerprint``).
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping, Sequence

from e3cm_bench.storage.run_config import RunConfig

FINGERPRINT = "fingerprint"  # the summary's column
ESTIMATOR_PACKAGES = ("opencv-python-headless", "poselib", "pycolmap")
INTERVAL_ONLY = ("interval_seeds",)  # evaluation settings that change the interval, not a number
# The evaluation settings hashed as ``sfm.*`` items: the keys older sfm records held as
# dataset.protocol, so that a run's fingerprint did not move when they became evaluation options
# (a fixed list: the hash's items are a format, not a copy of the option table).
SFM_ITEMS = ("mapper", "mapper_seeds", "merge", "merge_px", "verification", "score_model")


def _flat(prefix: str, value, out: dict) -> None:
    if isinstance(value, Mapping):
        for key in sorted(value, key=str):
            _flat(f"{prefix}.{key}", value[key], out)
    elif isinstance(value, (list, tuple)):
        out[prefix] = ",".join(str(v) for v in value)
    else:
        out[prefix] = str(value)


def protocol_items(config: RunConfig | Mapping) -> dict[str, str]:
    """`name -> value` of everything the fingerprint covers (the module docstring), in a fixed order."""
    if not isinstance(config, RunConfig):
        config = RunConfig.from_dict(dict(config))
    versions = config.versions or {}
    items: dict[str, str] = {}
    evaluation = {k: v for k, v in (config.evaluation or {}).items() if k not in INTERVAL_ONLY}
    protocol = {k: evaluation.pop(k) for k in SFM_ITEMS if k in evaluation}
    _flat("evaluation", evaluation, items)
    older = (config.dataset or {}).get("protocol")  # an older sfm record's (a pose set's "protocol" is a name)
    protocol = dict(older) if isinstance(older, Mapping) else protocol
    if protocol:
        _flat("sfm", protocol, items)
    for name in ESTIMATOR_PACKAGES:
        items[f"version.{name}"] = str(versions.get(name, "not recorded"))
    return items


def fingerprint(items: Mapping[str, str]) -> str:
    """Ten hex digits of the sha256 of the items, one `name=value` line each."""
    text = "\n".join(f"{name}={value}" for name, value in items.items())
    return hashlib.sha256(text.encode()).hexdigest()[:10]


def of_config(config: RunConfig | Mapping) -> str:
    return fingerprint(protocol_items(config))


def differences(before: Mapping[str, str], now: Mapping[str, str]) -> list[str]:
    """``name before -> now`` for each item that differs (absent on one side: 'absent')."""
    names = list(before) + [n for n in now if n not in before]
    return [f"{name} {before.get(name, 'absent')} -> {now.get(name, 'absent')}"
            for name in names if before.get(name) != now.get(name)]


def protocol_notes(labelled: Sequence[tuple[str, Mapping[str, str]]]) -> list[str]:
    """One line per run whose protocol differs from the first run's: its label, both
    fingerprints and what differs; [] where every run has the first run's fingerprint."""
    if len(labelled) < 2:
        return []
    first_label, first = labelled[0]
    notes = []
    for label, items in labelled[1:]:
        changed = differences(first, items)
        if changed:
            notes.append(f"protocol differs: {label} ({fingerprint(items)}) vs {first_label} ({fingerprint(first)}): "
                         + ", ".join(changed))
    return notes
