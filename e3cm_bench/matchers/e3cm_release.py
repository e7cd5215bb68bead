"""`e3cm-release`: the E3CM authors' released matcher (match_large_img + refinement_pose_ransac).

The algorithm is matching/release.py; the paper as written is `e3cm` (matchers/e3cm.py).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np

from e3cm_bench.backbones.pyramid import Backbone
from e3cm_bench.matching.release import RATIO_AT, ReleaseCascade, level_points, release_cascade, release_levels
from e3cm_bench.matchers.base import Matches
from e3cm_bench.matchers.deep import DeepMatcher, level0_cosine


@dataclass(frozen=True)
class E3CMReleaseSettings:
    """ratio: per level 0..4, the deepest level used takes its own entry (the release's
    config.yml: 0.9 with 0.95 at conv5_3; with 4 levels, match_small_img, conv4_2 takes 0.9).
    cascade: refinement_pose_ransac on (off: the uncascaded level-0 list). ratio_at, dedup:
    the release's refinement (matching/release.py)."""

    ratio: tuple[float, ...] = (0.9, 0.9, 0.9, 0.9, 0.95)
    cascade: bool = True
    residual: float = 0.01
    ransac_px: float = 1.0
    ratio_at: str = "own"
    dedup: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "ratio", tuple(float(r) for r in self.ratio))
        if len(self.ratio) < 5:
            raise ValueError("ratio needs 5 values (levels 0..4)")
        if self.ratio_at not in RATIO_AT:
            raise ValueError(f"ratio_at must be one of {', '.join(RATIO_AT)}, got {self.ratio_at!r}")


class E3CMReleaseMatcher(DeepMatcher):
    # The release keeps the points of padding cells (matching/release.py).
    keypoints_in_image = False

    def __init__(self, backbone: Backbone, settings: E3CMReleaseSettings | None = None, name: str = "e3cm-release",
                 channel_order: str = "rgb"):
        super().__init__(backbone, name, channel_order)
        self.settings = settings or E3CMReleaseSettings()

    def match(self, image0: np.ndarray, image1: np.ndarray) -> Matches:
        s = self.settings
        feats0, feats1, t_backbone = self.pyramids(image0, image1)
        t = time.perf_counter()
        cells0, cells1 = release_levels(feats0, feats1, s.ratio, s.ratio_at, s.dedup)
        top = len(cells0) - 1
        points0 = [level_points(c, top - i) for i, c in enumerate(cells0)]
        points1 = [level_points(c, top - i) for i, c in enumerate(cells1)]
        timings = {"backbone": t_backbone, "levels": time.perf_counter() - t}
        info: dict = {"counts": {top - i: len(c) for i, c in enumerate(cells0)}}
        x0, x1 = points0[-1], points1[-1]
        if s.cascade:
            t = time.perf_counter()
            out = release_cascade(points0, points1, ReleaseCascade(s.residual, s.ransac_px))
            x0, x1 = out["points0"], out["points1"]
            info["cascade_counts"] = {top - i: n for i, n in out["counts"].items()}
            info["cascade_fallback"] = out["fallback"]
            # By level: skipped (fewer than 8 matches), no F, or OpenCV's stacked 7-point solutions.
            info["cascade_notes"] = {top - i: note for i, note in out["notes"].items()}
            timings["cascade"] = time.perf_counter() - t
        info["timings"] = timings
        return Matches(x0, x1, level0_cosine(feats0[0], feats1[0], x0, x1), info)

    def settings_dict(self) -> dict:
        d = asdict(self.settings)
        d["ratio"] = list(self.settings.ratio)
        return d
