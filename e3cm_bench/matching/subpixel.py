"""Sub-pixel refinement of final matches on the images themselves (training-free).

Level-0 keypoints of the cascade sit on whole pixels of the level-0 map; this moves each
match's point in image B to where a fit of the patch around A's point says it is, and keeps the
move only where it is consistent. Two fits (`REFINE_MODES`; "-strict" = drop the inconsistent):

`lk` (`refine_lk`): OpenCV's pyramidal Lucas-Kanade (`calcOpticalFlowPyrLK`) started at the
match (initial flow), in a `window` x `window` patch, on one pyramid level above the image;
- forward-backward: B's refined point tracked back into A must land within `fb_px` of A's
  point;
- the move is at most `max_move` pixels (a refinement, never a new match).
LK assumes brightness constancy: across an illumination change few matches pass its checks.
OpenCV's LK takes two images of one size only: images that differ are padded right and bottom
to their common size (`common_size`), which moves no coordinate; a refined point must still
lie inside B's own extent.

`lk-auto` (`refine_lk_auto`): strict where LK fits the pair, lenient where it does not. LK
fits a pair when at least `ADAPTIVE_MIN_PASS` of its matches pass the checks: then those that
fail are dropped. It is tried on the grey levels first, then on each image's local contrast
(`local_contrast`: the grey level minus its Gaussian-weighted mean, over its Gaussian-weighted
standard deviation, sigma `CONTRAST_SIGMA` px), where a change of gain and offset leaves the
patches alike (an illumination change). Where neither fits, nothing is dropped and only the
matches that pass on the grey levels move (`lk`): LK moves a patch without turning or scaling
it, so under a large rotation or scale change nearly every match fails, and the failures say
that the model does not fit, not that the matches are wrong.

`ncc` (`refine_ncc`): zero-mean normalised cross-correlation of A's `window` x `window` patch
(bilinear, at A's possibly sub-pixel point) with B at whole-pixel offsets within +-`radius`
of B's point, and a 2-D quadratic fitted to the 3 x 3 NCC values around the best offset for
the sub-pixel peak. Zero-mean NCC is invariant to an affine brightness change (gain and
offset) of either patch, and nearly so to a smooth monotone one (gamma); kept only where
the best offset is interior, its NCC >= `min_ncc`, the quadratic is concave, the move is at
most `max_move` pixels and the result is finite and inside B.

A match whose fit fails its checks keeps its point (`drop=False`) or is dropped
(`drop=True`: the strict variant). No match is ever added; A's point never moves. Arrays in,
arrays out; pixel-centre coordinates (OpenCV's too). Deterministic: neither fit has
randomness.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

REFINE_MODES = ("none", "lk", "lk-strict", "lk-auto", "ncc", "ncc-strict")
# lk-auto: the share of a pair's matches that must pass LK's checks for the failing ones to be
# dropped, and the local contrast's Gaussian sigma (px). The share was chosen on the shared
# HPatches pairs (docs/methods.md, "Sub-pixel refinement"): on the grey levels LK passes 0-6 %
# of the e3cm-plus matches of the illumination pairs (68-83 % on local contrast) and 0-14 % of
# the viewpoint pairs', but 46 % of v_boat 1-2's (small turn and zoom, where dropping helps).
ADAPTIVE_MIN_PASS = 0.3
CONTRAST_SIGMA = 8.0


def check_refine(mode: str, window: int) -> None:
    """ValueError naming the setting unless `mode` is one of REFINE_MODES and `window` an odd
    number of pixels from 3 to 31 (the refine / refine_window settings of e3cm and e3cm-plus)."""
    if mode not in REFINE_MODES:
        raise ValueError(f"refine must be one of {', '.join(REFINE_MODES)}, got {mode!r}")
    if not (isinstance(window, int) and 3 <= window <= 31 and window % 2):
        raise ValueError(f"refine_window must be an odd number of pixels from 3 to 31, got {window!r}")


def _grey(image: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image


def common_size(grey0: np.ndarray, grey1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Both images as they are where their sizes agree; else each padded on the right and at
    the bottom to the larger width and height, by mirroring without repeating the edge
    (BORDER_REFLECT_101). OpenCV's LK asserts that its two pyramids have one size level by
    level. Padding right and bottom leaves every pixel, so every coordinate, where it was; and
    OpenCV builds each pyramid over a BORDER_REFLECT_101 border of its own, so within an
    image's own extent its pyramid levels are what they were unpadded (pyrDown reads the
    same mirrored pixels). Only a window reaching past the smaller image's edge sees
    different gradients there: mirrored content where unpadded it sees none."""
    (h0, w0), (h1, w1) = grey0.shape[:2], grey1.shape[:2]
    if (h0, w0) == (h1, w1):
        return grey0, grey1
    h, w = max(h0, h1), max(w0, w1)

    def pad(grey: np.ndarray) -> np.ndarray:
        return cv2.copyMakeBorder(grey, 0, h - grey.shape[0], 0, w - grey.shape[1], cv2.BORDER_REFLECT_101)

    return pad(grey0), pad(grey1)


def local_contrast(image: np.ndarray, sigma: float = CONTRAST_SIGMA) -> np.ndarray:
    """The grey image's local contrast as uint8 (LK's input type): (grey - local mean) / local
    standard deviation, both Gaussian-weighted with `sigma` px, mapped to 128 + 40 x that and
    clipped. An affine brightness change (gain > 0, offset) of the image leaves it unchanged
    up to rounding; the standard deviation is floored at 1 grey level (flat areas)."""
    grey = _grey(image).astype(np.float32)
    mean = cv2.GaussianBlur(grey, (0, 0), sigma)
    var = cv2.GaussianBlur(grey * grey, (0, 0), sigma) - mean * mean
    z = (grey - mean) / np.sqrt(np.maximum(var, 1.0))
    return np.clip(np.rint(128 + 40 * z), 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class LKFit:
    """refine_lk's fit: the patch side (pixels), the largest move, the forward-backward
    tolerance (pixels), and normalise: LK on the images' local contrast (`local_contrast`)
    instead of their grey levels."""

    window: int = 9
    max_move: float = 1.5
    fb_px: float = 0.3
    normalise: bool = False


@dataclass(frozen=True)
class NCCFit:
    """refine_ncc's fit: the patch side (pixels, odd), the search radius (whole pixels), the
    largest move and the lowest NCC kept (the defaults' reasons: refine_ncc's docstring)."""

    window: int = 9
    radius: int = 2
    max_move: float = 1.5
    min_ncc: float = 0.7


def refine_lk(image0: np.ndarray, image1: np.ndarray, kpts0: np.ndarray, kpts1: np.ndarray, fit: LKFit = LKFit(),
              drop: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(kpts1 refined, keep): kpts1 moved by LK (`fit`) where consistent; keep[i] False only for
    a match the strict variant drops. kpts0 never moves."""
    window, max_move, fb_px, normalise = fit.window, fit.max_move, fit.fb_px, fit.normalise
    kpts0 = np.asarray(kpts0, np.float32).reshape(-1, 2)
    kpts1 = np.asarray(kpts1, np.float32).reshape(-1, 2)
    keep = np.ones(len(kpts0), bool)
    if len(kpts0) == 0:
        return kpts1.copy(), keep
    grey0, grey1 = (local_contrast(image0), local_contrast(image1)) if normalise else (_grey(image0), _grey(image1))
    h, w = grey1.shape[:2]  # B's own extent, which a refined point must stay in
    grey0, grey1 = common_size(grey0, grey1)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
    options = dict(winSize=(window, window), maxLevel=1, criteria=criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    moved, status, _ = cv2.calcOpticalFlowPyrLK(
        grey0, grey1, kpts0.reshape(-1, 1, 2), kpts1.reshape(-1, 1, 2).copy(), **options
    )
    back, status_back, _ = cv2.calcOpticalFlowPyrLK(grey1, grey0, moved, kpts0.reshape(-1, 1, 2).copy(), **options)
    moved, back = moved.reshape(-1, 2), back.reshape(-1, 2)
    consistent = (status.ravel() == 1) & (status_back.ravel() == 1) \
        & (np.linalg.norm(back - kpts0, axis=1) <= fb_px) \
        & (np.abs(moved - kpts1).max(axis=1) <= max_move) & np.isfinite(moved).all(axis=1)
    consistent &= (moved[:, 0] >= 0) & (moved[:, 0] <= w - 1) & (moved[:, 1] >= 0) & (moved[:, 1] <= h - 1)
    refined = np.where(consistent[:, None], moved, kpts1)
    if drop:
        keep = consistent
    return refined.astype(np.float32), keep


def refine_lk_auto(image0: np.ndarray, image1: np.ndarray, kpts0: np.ndarray, kpts1: np.ndarray,
                   window: int = 9) -> tuple[np.ndarray, np.ndarray, str]:
    """(kpts1 refined, keep, what was used): strict LK on the grey levels where at least
    ADAPTIVE_MIN_PASS of the matches pass its checks ("grey"), else strict LK on the local
    contrast where that many pass there ("contrast"), else lenient LK on the grey levels
    ("lenient": nothing dropped)."""
    grey, passed = refine_lk(image0, image1, kpts0, kpts1, LKFit(window=window), drop=True)
    if len(passed) == 0 or passed.mean() >= ADAPTIVE_MIN_PASS:
        return grey, passed, "grey"
    contrast, passed_contrast = refine_lk(image0, image1, kpts0, kpts1, LKFit(window=window, normalise=True), drop=True)
    if passed_contrast.mean() >= ADAPTIVE_MIN_PASS:
        return contrast, passed_contrast, "contrast"
    return grey, np.ones(len(passed), bool), "lenient"


def _patches(grey: np.ndarray, centres: np.ndarray, side: int) -> np.ndarray:
    """N x side x side float64 patches of `grey` (H x W float64) centred on `centres` (N x 2,
    pixel-centre x, y; side odd): bilinear with exact weights, border replicated, i.e.
    cv2.getRectSubPix's sampling without a per-match call. The patch's samples are whole pixels
    apart, so one (side + 1)^2 block per match and its fractional offset give all of them."""
    h, w = grey.shape
    corner = centres - (side - 1) / 2  # the top-left sample
    base = np.floor(corner)
    fx, fy = (corner - base).T[:, :, None, None]  # each N x 1 x 1
    steps = np.arange(side + 1)
    xs = np.clip(base[:, 0:1].astype(np.intp) + steps, 0, w - 1)  # N x (side + 1)
    ys = np.clip(base[:, 1:2].astype(np.intp) + steps, 0, h - 1)
    block = grey[ys[:, :, None], xs[:, None, :]]
    rows = block[:, :, :-1] * (1 - fx) + block[:, :, 1:] * fx  # N x (side + 1) x side
    return rows[:, :-1] * (1 - fy) + rows[:, 1:] * fy


def _window_sums(values: np.ndarray, k: int) -> np.ndarray:
    """N x S x S sums of every k x k window of N x M x M `values` (S = M - k + 1), by an
    integral image."""
    n, m = values.shape[:2]
    integral = np.zeros((n, m + 1, m + 1))
    integral[:, 1:, 1:] = values.cumsum(axis=1).cumsum(axis=2)
    return integral[:, k:, k:] - integral[:, :-k, k:] - integral[:, k:, :-k] + integral[:, :-k, :-k]


def _ncc_surfaces(template: np.ndarray, search: np.ndarray) -> np.ndarray:
    """N x S x S zero-mean NCC of each k x k template with every k x k window of its M x M
    search patch (S = M - k + 1); NaN where the template or the window is flat (NCC undefined)."""
    n, k = template.shape[:2]
    t = template - template.mean(axis=(1, 2), keepdims=True)
    t_norm = np.sqrt((t * t).sum(axis=(1, 2)))
    windows = np.lib.stride_tricks.sliding_window_view(search, (k, k), axis=(1, 2))  # N x S x S x k x k (a view)
    # sum(t * window) = sum(t * (window - its mean)) since t sums to 0: the window's mean needs no removal here
    cross = np.einsum("nij,nabij->nab", t, windows, optimize=True)
    sums = _window_sums(search, k)
    w_norm = np.sqrt(np.maximum(_window_sums(search * search, k) - sums * sums / (k * k), 0.0))
    denom = t_norm[:, None, None] * w_norm
    # flat: denom is k^2 x the product of the two patches' standard deviations (grey levels);
    # a product under 1e-9 is zero up to rounding
    flat = denom <= 1e-9 * (k * k)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(flat, np.nan, cross / np.where(flat, 1.0, denom))


def _quadratic_fit() -> np.ndarray:
    """6 x 9 least-squares map from the 3 x 3 values at offsets dx, dy in {-1, 0, 1} (row-major,
    dy outer) to the coefficients of c0 + gx dx + gy dy + hxx dx^2 + hxy dx dy + hyy dy^2."""
    dy, dx = np.mgrid[-1:2, -1:2].reshape(2, -1).astype(np.float64)
    return np.linalg.pinv(np.stack([np.ones(9), dx, dy, dx * dx, dx * dy, dy * dy], axis=1))


_QUADRATIC_FIT = _quadratic_fit()


def refine_ncc(image0: np.ndarray, image1: np.ndarray, kpts0: np.ndarray, kpts1: np.ndarray, fit: NCCFit = NCCFit(),
               drop: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(kpts1 refined, keep): kpts1 moved to the sub-pixel peak of the zero-mean NCC of A's
    `window` x `window` patch at kpts0 with B around kpts1 (whole-pixel offsets within
    +-`radius`, then a 2-D quadratic fitted to the 3 x 3 values around the best one) where
    consistent; keep[i] False only for a match the strict variant drops. kpts0 never moves.

    Consistent: the NCC is defined, the best offset is interior (not on the search border, so
    the peak lies inside the searched range), its NCC >= `min_ncc`, the quadratic is concave
    with its peak within the 3 x 3 it was fitted on, the move is at most `max_move` pixels
    (Euclidean) and the result is finite and inside B.

    min_ncc 0.7: on HPatches with the ground-truth homographies (corners of image 1, starts
    within about a pixel of the truth) 0.7 is the knee: it keeps 82-92 % of the i_leuven 1-k
    matches (0.5 keeps 83-92 %, 0.8 only 74-88 %), while of deliberate wrong starts 4-12 px
    off at most 1 % pass (2-4 % at 0.5). radius 2: the best whole-pixel offset must be
    interior, so radius 2 allows +-1 pixel plus the sub-pixel part, about max_move's 1.5 px;
    a larger radius would only add offsets that max_move rejects. window 9: LK's, so that
    `refine_window` means the same patch side for both (11-15 measured slightly more
    accurate on the test image, at a coarser footprint). `fit` holds the four (NCCFit).
    """
    window, radius, max_move, min_ncc = fit.window, fit.radius, fit.max_move, fit.min_ncc
    if not (isinstance(window, (int, np.integer)) and window >= 3 and window % 2):
        raise ValueError(f"refine_ncc: window must be an odd number of pixels >= 3, got {window!r}")
    if not (isinstance(radius, (int, np.integer)) and radius >= 1):
        raise ValueError(f"refine_ncc: radius must be a whole number of pixels >= 1, got {radius!r}")
    kpts0 = np.asarray(kpts0, np.float32).reshape(-1, 2)
    kpts1 = np.asarray(kpts1, np.float32).reshape(-1, 2)
    n = len(kpts0)
    keep = np.ones(n, bool)
    if n == 0:
        return kpts1.copy(), keep
    grey0, grey1 = _grey(image0).astype(np.float64), _grey(image1).astype(np.float64)
    p0, p1 = kpts0.astype(np.float64), kpts1.astype(np.float64)
    finite = np.isfinite(p0).all(axis=1) & np.isfinite(p1).all(axis=1)
    p0, p1 = np.where(finite[:, None], p0, 0.0), np.where(finite[:, None], p1, 0.0)  # sampled, then rejected
    ncc = _ncc_surfaces(_patches(grey0, p0, window), _patches(grey1, p1, window + 2 * radius))  # N x side x side
    side = 2 * radius + 1
    scores = np.where(np.isnan(ncc), -np.inf, ncc).reshape(n, -1)
    best = scores.argmax(axis=1)  # the first of equal maxima: deterministic
    by, bx = np.divmod(best, side)
    peak = scores[np.arange(n), best]
    interior = (bx >= 1) & (bx <= side - 2) & (by >= 1) & (by <= side - 2)
    sx, sy, concave = _quadratic_peak(ncc, bx, by)
    moved = p1 + np.stack([bx - radius + sx, by - radius + sy], axis=1)
    h, w = grey1.shape
    with np.errstate(invalid="ignore"):
        # min_ncc: the default's reason is in the docstring (measured knee on HPatches)
        consistent = finite & interior & (peak >= min_ncc) & concave & np.isfinite(moved).all(axis=1) \
            & (np.linalg.norm(moved - p1, axis=1) <= max_move) \
            & (moved[:, 0] >= 0) & (moved[:, 0] <= w - 1) & (moved[:, 1] >= 0) & (moved[:, 1] <= h - 1)
    refined = np.where(consistent[:, None], moved.astype(np.float32), kpts1)
    if drop:
        keep = consistent
    return refined.astype(np.float32), keep


def _quadratic_peak(ncc: np.ndarray, bx: np.ndarray, by: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(sx, sy, concave): the sub-pixel peak of the quadratic fitted to the 3 x 3 NCC values
    around each surface's best whole-pixel offset (bx, by), and whether it is a peak inside
    that 3 x 3 (N x side x side surfaces; each result N)."""
    n, side = len(ncc), ncc.shape[1]
    cy, cx = np.clip(by, 1, side - 2), np.clip(bx, 1, side - 2)  # (clipped only where rejected anyway)
    around = np.arange(-1, 2)
    rows, cols = (cy[:, None] + around)[:, :, None], (cx[:, None] + around)[:, None, :]
    neighbours = ncc[np.arange(n)[:, None, None], rows, cols]  # N x 3 x 3 around the best offset
    _, gx, gy, hxx, hxy, hyy = _QUADRATIC_FIT @ neighbours.reshape(n, 9).T  # each N; NaN if a value is
    det = 4 * hxx * hyy - hxy * hxy  # of the Hessian [[2 hxx, hxy], [hxy, 2 hyy]]
    concave = (hxx < 0) & (det > 0)
    safe = np.where(concave, det, 1.0)
    sx = (hxy * gy - 2 * hyy * gx) / safe  # the stationary point: Hessian^-1 (-gradient)
    sy = (hxy * gx - 2 * hxx * gy) / safe
    concave &= (np.abs(sx) <= 1) & (np.abs(sy) <= 1)  # a peak outside the fitted 3 x 3 is extrapolated
    return sx, sy, concave


def refine_matches(image0: np.ndarray, image1: np.ndarray, kpts0: np.ndarray, kpts1: np.ndarray, mode: str,
                   window: int = 9) -> tuple[np.ndarray, np.ndarray]:
    """(B's points, kept mask) after refinement `mode` (REFINE_MODES; "none" moves nothing):
    the setting of the cascade matchers, one place for e3cm and e3cm-plus."""
    check_refine(mode, window)
    if mode == "none":
        return kpts1, np.ones(len(kpts1), bool)
    if mode == "lk-auto":
        return refine_lk_auto(image0, image1, kpts0, kpts1, window=window)[:2]
    if mode.startswith("ncc"):
        return refine_ncc(image0, image1, kpts0, kpts1, NCCFit(window=window), drop=mode.endswith("-strict"))
    return refine_lk(image0, image1, kpts0, kpts1, LKFit(window=window), drop=mode.endswith("-strict"))
