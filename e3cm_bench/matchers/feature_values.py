"""What the feature cache holds, measured and written to disk: a backbone's pyramid (a list of
tensors) or a two-stage matcher's `Features` (named numpy arrays, tensors and plain values).

torch is imported only to write or read a file: a classical matcher's features (numpy) are
counted without it."""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING

import numpy as np

from e3cm_bench.matchers.base import Features

if TYPE_CHECKING:
    import torch

PLAIN = (bool, int, float, str, type(None))


def nbytes(value) -> int:
    """Bytes of the arrays in value (a tensor, an array, or a list, tuple or dict of them);
    a plain value counts nothing."""
    if isinstance(value, np.ndarray):
        return int(value.nbytes)
    torch = sys.modules.get("torch")
    if torch is not None and isinstance(value, torch.Tensor):
        return value.numel() * value.element_size()
    if isinstance(value, dict):
        return sum(nbytes(v) for v in value.values())
    if isinstance(value, (list, tuple)):
        return sum(nbytes(v) for v in value)
    return 0


def compact(
    maps: list[torch.Tensor], dtype: torch.dtype | None, exact: dict[int, bool] | None = None
) -> list[torch.Tensor]:
    """Each float32 map in `dtype` where that holds it exactly (maps a reduced-precision
    network computed, then widened), else as it is. exact: level -> whether that level's maps
    are exact in dtype, filled by checking the first map of each level: a level's maps come
    out of the same layer in the same precision for every image, so one check tells."""
    if dtype is None:
        return maps
    import torch

    exact = {} if exact is None else exact
    out = []
    for level, m in enumerate(maps):
        if m.dtype == torch.float32 and exact.get(level, True):
            narrow = m.to(dtype)
            if level not in exact:
                exact[level] = torch.equal(narrow.to(torch.float32), m)
            if exact[level]:
                m = narrow
        out.append(m)
    return out


def widen(maps: list[torch.Tensor]) -> list[torch.Tensor]:
    import torch

    return [m if m.dtype == torch.float32 or not m.is_floating_point() else m.to(torch.float32) for m in maps]


def portable(value):
    """value as torch.save writes it and torch.load(weights_only=True) reads it back: a
    pyramid's tensors on the CPU; Features as [name, kind, value] rows (numpy arrays as
    tensors, kind "numpy", to come back as arrays). None where a value of Features is neither
    an array nor plain (a number, a string, None or a tuple of them): it cannot wait on disk."""
    import torch

    if not isinstance(value, Features):
        return [m.cpu() for m in value]
    rows = []
    for name, item in value.items():
        if isinstance(item, np.ndarray) and item.dtype != object:
            rows.append([name, "numpy", torch.from_numpy(np.ascontiguousarray(item))])
        elif isinstance(item, torch.Tensor):
            rows.append([name, "torch", item.cpu()])
        elif isinstance(item, PLAIN) or (isinstance(item, tuple) and all(isinstance(v, PLAIN) for v in item)):
            rows.append([name, "plain", item])
        else:
            return None
    return {"features": rows}


def from_portable(loaded):
    """What `portable` wrote, as it was: Features come back with their arrays as numpy."""
    if not isinstance(loaded, dict):
        return loaded
    return Features({name: item.numpy() if kind == "numpy" else item for name, kind, item in loaded["features"]})
