"""What every benchmark dataset yields: pairs of image paths with their ground truth."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


class DatasetError(ValueError):
    """Bad or missing benchmark input; the message is one line naming the file and the problem."""


@dataclass
class Pair:
    """One image pair and its ground truth.

    ``name`` is unique within a dataset; it is the key of the pair in ``matches.h5`` and
    the ``pair`` column of ``per_pair.csv``. Homography pairs carry ``H`` (maps pixels of
    image 0 to image 1); pose pairs carry ``K0``, ``K1`` (original images) and ``T_0to1``
    (4x4, camera 0 to camera 1).
    """

    name: str
    image0: Path
    image1: Path
    H: np.ndarray | None = None
    K0: np.ndarray | None = None
    K1: np.ndarray | None = None
    T_0to1: np.ndarray | None = None
    meta: dict = field(default_factory=dict)  # e.g. {"sequence": "v_boat", "split": "v"}
