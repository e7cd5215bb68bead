"""Matches between two images: the one value every matcher returns and the cache stores.

numpy only (no torch), so that the cache, the metrics and the reports import it cheaply.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Matches:
    """Correspondences between two images.

    keypoints0, keypoints1: N x 2 float32, pixels of the images given to the matcher,
    pixel-centre convention (the centre of the top-left pixel is (0, 0)).
    scores: N float32, higher is more confident.
    info: diagnostics (per-level counts, the F used at each level, stage timings).
    """

    keypoints0: np.ndarray
    keypoints1: np.ndarray
    scores: np.ndarray
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.keypoints0 = np.asarray(self.keypoints0, dtype=np.float32).reshape(-1, 2)
        self.keypoints1 = np.asarray(self.keypoints1, dtype=np.float32).reshape(-1, 2)
        self.scores = np.asarray(self.scores, dtype=np.float32).reshape(-1)

    def __len__(self) -> int:
        return len(self.keypoints0)
