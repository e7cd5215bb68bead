"""The E3CM matching pipeline on two feature pyramids: tensors in, a dict of arrays out.

initial mutual-NN + ratio at the deepest level -> for each level l = L-1 .. 1:
    [cascade] confidence of the level-l matches, F_l from them
    refine the matches to level l-1 (DFM 2x2 step)
    [cascade] drop the level-(l-1) candidates whose Sampson distance to F_l exceeds the
              threshold of level l-1
The result is at level 0 (one cell per original pixel).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F

from e3cm_bench.matching import SCORED_ESTIMATORS
from e3cm_bench.matching.cascade import (
    ESTIMATORS,
    UnitPixels,
    confidence_scores,
    epipolar_inliers,
    estimate_level_fundamental,
    pixel_norms,
    pixel_rows,
)
from e3cm_bench.matching.dense import match_dense_level
from e3cm_bench.matching.levels import cell_centres, valid_extent
from e3cm_bench.matching.norms import normalize_channels
from e3cm_bench.matching.refine import ChildTest, refine_to_children


# Sampson thresholds (px) for the candidates of levels 0..3, chosen on the shared data with
# EfficientNet-Lite0 (15 HPatches pairs, 31 KITTI pairs; docs/methods.md "Choosing the Sampson
# thresholds"): an 8-point F from 8 cell centres is coarse, so top-8 needs 4x the cell size of
# the F's level to keep good matches; a RANSAC F over all matches is accurate to half a cell.
DEFAULT_SAMPSON_PX = {
    "top8": (8.0, 16.0, 32.0, 64.0),
    "ransac": (1.0, 2.0, 4.0, 8.0),
    "prosac": (1.0, 2.0, 4.0, 8.0),
    "magsac": (1.0, 2.0, 4.0, 8.0),
}


@dataclass
class E3CMSettings:
    """Every knob of the pipeline (all of it is written next to the results).

    ratio: ratio-test threshold per level 0..4 (the deepest level used takes its own entry).
    sampson_px: rejection threshold in pixels for the candidates of level 0..3, i.e. the
        threshold applied after refining into that level with F of the level above.
        None takes the measured default of the estimator (DEFAULT_SAMPSON_PX; docs/methods.md).
    estimator: how F_l is estimated (top8 = the paper; ransac / prosac = ablations).
    ransac_cells: RANSAC threshold of F_l at level l, in cells of that level (x 2^l = pixels).
    ratio_at: refinement's B->A ratio read at the matched B child ("matched", as Eq. 2 states
        it) or at the A child's index ("own", as both releases do).
    valid_cells_only: only cells whose centres lie in the image take part and the dropped
        border ring is that of the valid cells (True); False = the releases' handling: the
        padding cells take part and the ring is that of the padded map.
    subpixel: move each level-0 keypoint of B to the peak of a parabola fitted to its
        similarity with A's pixel at B's pixel and its 4 neighbours (e3cm-plus; off in the
        paper).
    refine: sub-pixel refinement of the final matches on the images (matching/subpixel.py):
        none (the paper), lk (LK fit kept where forward-backward consistent), ncc (peak of the
        zero-mean NCC, invariant to affine brightness changes, kept where the peak is
        consistent); lk-strict / ncc-strict also drop the inconsistent matches; lk-auto: drops
        the inconsistent matches only where LK fits the pair (on the grey levels, or on the
        local contrast across an illumination change), else as lk;
        refine_window: the patch side in pixels (of either fit).
    """

    cascade: bool = True
    estimator: str = "top8"
    ratio: tuple[float, ...] = (0.9, 0.9, 0.9, 0.9, 0.9)
    sampson_px: tuple[float, ...] | None = None
    ransac_cells: float = 0.5
    max_per_parent: int = 2
    confidence_eps: float = 1e-3
    drop_border: bool = True
    dense_chunk: int = 2048
    ratio_at: str = "matched"
    valid_cells_only: bool = True
    subpixel: bool = False
    refine: str = "none"
    refine_window: int = 9

    def __post_init__(self) -> None:
        if self.ratio_at not in ("matched", "own"):
            raise ValueError(f"ratio_at must be 'matched' or 'own', got {self.ratio_at!r}")
        from e3cm_bench.matching.subpixel import check_refine

        check_refine(self.refine, self.refine_window)
        if self.estimator not in ESTIMATORS:
            raise ValueError(f"unknown cascade estimator {self.estimator!r}; choose one of {', '.join(ESTIMATORS)}")
        self.ratio = tuple(float(r) for r in self.ratio)
        if self.sampson_px is None:
            self.sampson_px = DEFAULT_SAMPSON_PX[self.estimator]
        self.sampson_px = tuple(float(s) for s in self.sampson_px)
        if len(self.ratio) < 5 or len(self.sampson_px) < 4:
            raise ValueError("ratio needs 5 values (levels 0..4) and sampson_px 4 (levels 0..3)")

    @property
    def reads_level0(self) -> bool:
        """Whether the cascade scores matches by their level-0 patches (top8, PROSAC): the
        only step that reads level 0 beyond the children of matches."""
        return self.cascade and self.estimator in SCORED_ESTIMATORS

    def to_dict(self) -> dict:
        d = asdict(self)
        d["ratio"] = list(self.ratio)
        d["sampson_px"] = list(self.sampson_px)
        return d


def subpixel_offsets(
    map0: torch.Tensor, map1: torch.Tensor, cells0: torch.Tensor, cells1: torch.Tensor
) -> torch.Tensor:
    """N x 2 offsets (dx, dy) in [-0.5, 0.5] of each level-0 match's B pixel towards the peak
    of the similarity to A's pixel: along each axis a parabola through the cosines at B's
    pixel and its two neighbours (an axis whose neighbour lies outside the map, or whose
    three values do not peak in the middle, is left at 0).

    map0/map1: level-0 maps (C x H x W, not necessarily normalised); cells: N x 2 (x, y).
    """
    if len(cells0) == 0:
        return torch.zeros(0, 2, dtype=torch.float64)
    a = F.normalize(map0[:, cells0[:, 1], cells0[:, 0]], dim=0)  # C x N

    def cosine_to_a(cells: torch.Tensor) -> torch.Tensor:  # N cosines of A's pixels with B's at `cells`
        return (a * F.normalize(map1[:, cells[:, 1], cells[:, 0]], dim=0)).sum(0).double().cpu()

    h, w = map1.shape[1:]
    offsets = torch.zeros(len(cells0), 2, dtype=torch.float64)
    centre = cosine_to_a(cells1)
    for axis, limit in ((0, w), (1, h)):
        step = torch.zeros(2, dtype=cells1.dtype, device=cells1.device)
        step[axis] = 1
        before, after = cells1 - step, cells1 + step
        inside = (before[:, axis] >= 0) & (after[:, axis] < limit)
        before, after = before.clamp_min(0), after.clone()
        after[:, axis] = after[:, axis].clamp_max(limit - 1)
        s_before, s_after = cosine_to_a(before), cosine_to_a(after)
        curvature = s_before - 2 * centre + s_after
        peaked = inside.cpu() & (curvature < 0) & (centre >= s_before) & (centre >= s_after)
        shift = 0.5 * (s_before - s_after) / torch.where(peaked, curvature, torch.ones_like(curvature))
        offsets[:, axis] = torch.where(peaked, shift.clamp(-0.5, 0.5), torch.zeros_like(shift))
    return offsets


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().numpy()


def match_pyramids(
    feats0: list[torch.Tensor],
    feats1: list[torch.Tensor],
    size0: tuple[int, int],
    size1: tuple[int, int],
    settings: E3CMSettings,
    memo: Callable[[int, str, Callable[[], torch.Tensor]], torch.Tensor] | None = None,
) -> dict:
    """Match two feature pyramids (level l: C_l x H_l x W_l, stride 2^l in original pixels).

    size0/size1: (width, height) of the original images (the maps may cover padding).
    memo(side, name, compute): how a product of one image's maps alone is obtained (side 0 or
    1; the name says what it is); the default computes it. A matcher whose images recur over
    a run's pairs passes one that keeps them (DeepMatcher.image_product).
    Returns keypoints0/1 (N x 2 float, original pixels), scores (cosine similarity at
    level 0), and diagnostics: per-level counts before/after rejection, the F of each
    level, whether rejection ran, and stage times in seconds.
    """
    top = len(feats0) - 1
    timings: dict[str, float] = {}
    extents = _level_extents(feats0, feats1, size0, size1, settings)
    unit0, unit1, top0, top1 = _normalised(feats0, feats1, settings, _computed if memo is None else memo, timings)
    t = time.perf_counter()
    cells0, cells1, dist = match_dense_level(
        top0, top1, *extents(top), settings.ratio[top], settings.drop_border, settings.dense_chunk,
    )
    timings["initial"] = time.perf_counter() - t
    counts_before, counts_after = {top: len(cells0)}, {top: len(cells0)}
    fundamentals: dict[int, np.ndarray | None] = {}
    rejection: dict[int, str] = {}
    timings["cascade"] = 0.0
    for level in range(top, 0, -1):
        F_l = None
        if settings.cascade:
            t = time.perf_counter()
            F_l = _level_fundamental(unit0, unit1, cells0, cells1, level, settings)
            fundamentals[level] = F_l
            timings["cascade"] += time.perf_counter() - t
        t = time.perf_counter()
        cells0, cells1, dist, _ = refine_to_children(
            feats0[level - 1], feats1[level - 1], cells0, cells1,
            *extents(level - 1), ChildTest(settings.ratio[level - 1], settings.max_per_parent, settings.ratio_at),
        )
        timings[f"refine_l{level - 1}"] = time.perf_counter() - t
        counts_before[level - 1] = len(cells0)
        if settings.cascade:
            t = time.perf_counter()
            cells0, cells1, dist, rejection[level - 1] = _epipolar_rejection(
                F_l, cells0, cells1, dist, level, counts_after[level], settings)
            timings["cascade"] += time.perf_counter() - t
        counts_after[level - 1] = len(cells0)
    return {
        **_keypoints(feats0, feats1, cells0, cells1, dist, settings, timings),
        "counts_before": counts_before,
        "counts_after": counts_after,
        "fundamentals": fundamentals,
        "rejection": rejection,
        "timings": timings,
    }


def _computed(side: int, name: str, compute: Callable[[], torch.Tensor]) -> torch.Tensor:
    """match_pyramids' memo where none is given: every product computed."""
    return compute()


def _level_extents(feats0: list[torch.Tensor], feats1: list[torch.Tensor], size0: tuple[int, int],
                   size1: tuple[int, int], settings: E3CMSettings) -> Callable[[int], tuple]:
    """level -> the (w, h) in cells of each image's map matched at that level."""
    def extents(level: int) -> tuple[tuple[int, int], tuple[int, int]]:
        if settings.valid_cells_only:
            return valid_extent(size0, level), valid_extent(size1, level)
        return (feats0[level].shape[2], feats0[level].shape[1]), (feats1[level].shape[2], feats1[level].shape[1])

    return extents


def _normalised(feats0: list[torch.Tensor], feats1: list[torch.Tensor], settings: E3CMSettings, memo,
                timings: dict[str, float]) -> tuple:
    """(unit0, unit1, top0, top1): each image's level 0 as UnitPixels (None where nothing reads
    it) and its deepest level normalised; the time taken goes to timings["normalise"]."""
    # The deepest level is matched densely, so it is normalised whole. Level 0 is read by the
    # confidence score only (top8 and PROSAC), patch by patch, as pixel rows divided by their
    # norms as they are gathered (UnitPixels): the rows are the backbone's own channels-last
    # output where the matcher kept it (memo "pixel_rows:0"), else a copy; only the norms
    # are computed from the whole map. The levels between are read only at children of
    # matches: refine_to_children normalises those as it reads them.
    top = len(feats0) - 1
    t = time.perf_counter()
    unit0 = unit1 = None

    def level0_pixels(side: int, feat: torch.Tensor) -> UnitPixels:
        return UnitPixels.of(feat, memo(side, "pixel_rows:0", lambda: pixel_rows(feat)),
                             memo(side, "pixel_norms:0", lambda: pixel_norms(feat)))

    if settings.reads_level0:
        unit0, unit1 = level0_pixels(0, feats0[0]), level0_pixels(1, feats1[0])
    top0 = memo(0, f"normalize:{top}", lambda: normalize_channels(feats0[top]))
    top1 = memo(1, f"normalize:{top}", lambda: normalize_channels(feats1[top]))
    timings["normalise"] = time.perf_counter() - t
    return unit0, unit1, top0, top1


def _level_fundamental(unit0: UnitPixels | None, unit1: UnitPixels | None, cells0: torch.Tensor,
                       cells1: torch.Tensor, level: int, settings: E3CMSettings) -> np.ndarray | None:
    """The cascade's F at `level`, from the matches' cell centres (scored where the estimator
    reads confidences); None where it cannot be estimated."""
    x0 = _np(cell_centres(cells0, level))
    x1 = _np(cell_centres(cells1, level))
    conf = None
    if settings.estimator in SCORED_ESTIMATORS and len(cells0) >= 8:
        # top-8 needs only the 8 best scores (the rest stay -inf); PROSAC orders them all.
        top = 8 if settings.estimator == "top8" else None
        conf = _np(confidence_scores(unit0, unit1, cells0, cells1, level, settings.confidence_eps, top=top))
    return estimate_level_fundamental(x0, x1, conf, settings.estimator, settings.ransac_cells * 2**level)


def _epipolar_rejection(F_l: np.ndarray | None, cells0: torch.Tensor, cells1: torch.Tensor, dist: torch.Tensor,
                        level: int, matched_above: int, settings: E3CMSettings) -> tuple:
    """(cells0, cells1, dist, what rejection did): the children of level-1 kept where they fit
    the F of `level` (all of them where there is none; matched_above: the matches at `level`)."""
    if F_l is None:
        why = "fewer than 8 matches" if matched_above < 8 else "degenerate F"
        return cells0, cells1, dist, f"skipped: {why} at level {level}"
    keep = epipolar_inliers(
        F_l, _np(cell_centres(cells0, level - 1)), _np(cell_centres(cells1, level - 1)),
        settings.sampson_px[level - 1],
    )
    keep_t = torch.from_numpy(keep).to(cells0.device)
    return cells0[keep_t], cells1[keep_t], dist[keep_t], "applied"


def _keypoints(feats0: list[torch.Tensor], feats1: list[torch.Tensor], cells0: torch.Tensor, cells1: torch.Tensor,
               dist: torch.Tensor, settings: E3CMSettings, timings: dict[str, float]) -> dict:
    """keypoints0/1 (original pixels; B's moved by the sub-pixel offsets where set) and scores."""
    keypoints1 = _np(cell_centres(cells1, 0))
    if settings.subpixel:
        t = time.perf_counter()
        keypoints1 = keypoints1 + _np(subpixel_offsets(feats0[0], feats1[0], cells0, cells1))
        timings["subpixel"] = time.perf_counter() - t
    return {
        "keypoints0": _np(cell_centres(cells0, 0)).astype(np.float32),
        "keypoints1": keypoints1.astype(np.float32),
        "scores": (1 - _np(dist)).astype(np.float32),
    }
