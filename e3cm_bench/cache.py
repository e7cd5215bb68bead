"""An HDF5 store of matches, one group per image pair, that survives interrupted runs.

A pair name such as ``"v_graffiti/1-2"`` becomes the nested group ``v_graffiti/1-2``
holding the datasets ``keypoints0``, ``keypoints1`` (N x 2 float32) and ``scores``
(N float32), plus the caller's attributes (image sizes, timings).

Crash safety comes from two rules. The file is opened for one write and closed right
after, so a run killed between pairs leaves a closed, consistent file. And the
attribute ``complete=1`` is set last, so a run killed in the middle of a write leaves
an entry that ``names`` and ``read`` ignore and the next run simply rewrites.
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from e3cm_bench.matches import Matches

DATASETS = ("keypoints0", "keypoints1", "scores")
COMPLETE_ATTR = "complete"


class MatchCache:
    """Matches of many image pairs in one HDF5 file, keyed by pair name."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    # ------------------------------------------------------------------ queries

    def names(self) -> list[str]:
        """The names of all complete entries, sorted."""
        if not self.path.exists():
            return []
        found: list[str] = []
        with self._open("r") as file:

            def collect(key: str, item: h5py.HLObject) -> None:
                if _is_complete(item):
                    found.append(key)

            file.visititems(collect)
        return sorted(found)

    def read(self, name: str) -> Matches:
        """The stored matches; ``info`` holds the attributes given to ``write``."""
        key = _group_key(name)
        if not self.path.exists():
            raise KeyError(f"no match cache at {self.path}")
        with self._open("r") as file:
            group = file.get(key)
            if not _is_complete(group):
                raise KeyError(f"pair {name!r} has no complete entry in {self.path}")
            info = {k: _plain(v) for k, v in group.attrs.items() if k != COMPLETE_ATTR}
            return Matches(
                keypoints0=group["keypoints0"][()],
                keypoints1=group["keypoints1"][()],
                scores=group["scores"][()],
                info=info,
            )

    # ---------------------------------------------------------------- mutations

    def write(self, name: str, matches: Matches, attrs: dict | None = None) -> None:
        """Store the matches of one pair, replacing any earlier (or half-written) entry.

        ``attrs`` values must be numbers, strings, booleans or arrays/sequences of them
        (what HDF5 attributes hold). ``matches.info`` is not stored: it is free-form
        diagnostics, while the attributes are what later stages need.
        """
        key = _group_key(name)
        attrs = dict(attrs or {})
        if COMPLETE_ATTR in attrs:
            raise ValueError(f"attribute name {COMPLETE_ATTR!r} is reserved by the match cache")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with self._open("a") as file:
            group = file.require_group(key)
            # Clear only this entry's own content: a group may also be the parent of
            # other pairs' groups (a name that prefixes another), which must survive.
            _clear_entry(group)
            for dataset, values in zip(DATASETS, (matches.keypoints0, matches.keypoints1, matches.scores)):
                group.create_dataset(dataset, data=values, compression="gzip", compression_opts=4)
            for attr, value in attrs.items():
                try:
                    group.attrs[attr] = value
                except (TypeError, ValueError) as error:
                    raise TypeError(
                        f"attribute {attr!r}={value!r} cannot be stored in HDF5 ({error})"
                    ) from error
            group.attrs[COMPLETE_ATTR] = 1  # last, so an interrupted write reads as absent

    # ------------------------------------------------------------------ helpers

    def _open(self, mode: str) -> h5py.File:
        # h5py reports a foreign file as a bare OSError; say which file and what to do.
        if self.path.exists() and not h5py.is_hdf5(self.path):
            raise ValueError(_not_hdf5_message(self.path))
        try:
            return h5py.File(self.path, mode)
        except OSError as error:
            if "signature" in str(error).lower() or "truncated" in str(error).lower():
                raise ValueError(_not_hdf5_message(self.path)) from error
            raise


def _not_hdf5_message(path: Path) -> str:
    return f"{path} is not a readable HDF5 match cache (delete it or rerun with --overwrite)"


def _group_key(name: str) -> str:
    """The HDF5 path of a pair; rejects names whose '/'-parts would collapse or escape."""
    parts = str(name).split("/")
    if not name or any(part in ("", ".", "..") for part in parts):
        raise ValueError(f"invalid pair name {name!r}: '/'-separated parts must be non-empty")
    return "/".join(parts)


def _is_complete(item: h5py.HLObject | None) -> bool:
    return isinstance(item, h5py.Group) and int(item.attrs.get(COMPLETE_ATTR, 0)) == 1


def _clear_entry(group: h5py.Group) -> None:
    # The completion mark goes first, so the entry is never complete while half-cleared.
    if COMPLETE_ATTR in group.attrs:
        del group.attrs[COMPLETE_ATTR]
    for attr in list(group.attrs):
        del group.attrs[attr]
    for dataset in DATASETS:
        if dataset in group:
            del group[dataset]


def _plain(value: object) -> object:
    """HDF5 attribute -> plain Python scalar / str, or a numpy array for sequences."""
    if isinstance(value, bytes):
        return value.decode("utf-8")
    if isinstance(value, np.generic):
        return value.item()
    return value
