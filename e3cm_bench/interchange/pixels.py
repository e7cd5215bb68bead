"""Pixel conventions at the boundary: the one conversion out and the one conversion in, and
the HPatches check that tells which convention a file was written in.

Ours: the centre of the top-left pixel is (0, 0) ("center"). The other: the top-left corner
of the top-left pixel is (0, 0), so that pixel's centre is (0.5, 0.5) ("corner", COLMAP's).
Each format's own is its Format's ``origin`` (registry.py); docs/interchange.md lists each tool
with the source line that shows its convention.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ORIGINS = ("center", "corner")
# Where the centre of the top-left pixel sits, per convention, in units of pixels.
_CENTRE_OF_FIRST_PIXEL = {"center": 0.0, "corner": 0.5}


def check_origin(origin: str) -> str:
    if origin not in ORIGINS:
        raise ValueError(f"--pixel-origin must be one of {', '.join(ORIGINS)}, got {origin!r}")
    return origin


def resolve_origin(fmt, given: str | None) -> str:
    """The pixel origin of a file in format `fmt` (a registry Format, read for its ``origin``):
    --pixel-origin as given, else the format's own. The one place that default is read: every
    reader, writer and `export` comes through here."""
    return check_origin(given or fmt.origin)


def to_origin(points: np.ndarray, origin: str) -> np.ndarray:
    """Our keypoints (N x 2, centre convention) in `origin`'s convention, as float64: adding
    0.5 to a float32 in float64 is exact, so a file that keeps float64 round-trips bit for bit."""
    return np.asarray(points, np.float64) + _CENTRE_OF_FIRST_PIXEL[check_origin(origin)]


def from_origin(points: np.ndarray, origin: str) -> np.ndarray:
    """Keypoints read in `origin`'s convention, in ours, as float64 (the run stores float32)."""
    return np.asarray(points, np.float64) - _CENTRE_OF_FIRST_PIXEL[check_origin(origin)]


# --------------------------------------------------------------------------- the check

# A shift must win by this many standard deviations of McNemar's statistic, and by this
# fraction of the matches, before we call the other convention clearly better: the pooled
# counts of one run are large, so significance alone would flag a shift of no practical size.
CHECK_Z = 3.0
CHECK_MIN_GAIN = 0.01
CHECK_PX = 1.0  # mma@1's threshold: the tightest of HPatches' MMA, where half a pixel shows most


@dataclass
class HalfPixelCheck:
    n_matches: int
    as_read: float  # fraction of matches within CHECK_PX of the ground truth, as imported
    shifted: float  # the same with both images' keypoints moved by `shift`
    shift: float  # -0.5 or +0.5 (pixels, added to x and y)
    z: float  # McNemar's statistic, positive when the shift fits better

    @property
    def other_fits_better(self) -> bool:
        return self.z > CHECK_Z and self.shifted - self.as_read > CHECK_MIN_GAIN

    def line(self) -> str:
        return (
            f"pixel convention check: mma@1 {self.as_read:.3f} as read, {self.shifted:.3f} with {self.shift:+.1f} px "
            f"on both images ({self.n_matches} matches, McNemar z {self.z:.1f})"
        )


def half_pixel_check(pairs_and_matches) -> HalfPixelCheck | None:
    """mma@1 of the imported matches with and without half a pixel on both images, pooled over
    the pairs that carry a homography (H maps image-0 pixels to image-1 pixels, our convention).
    A file written in the other convention is off by the same 0.5 px in both images; under a
    homography that is not a pure translation the error does not cancel, so the shifted copy
    fits the ground truth better. None when there is nothing to check."""
    from e3cm_bench.geometry.two_view import warp_points

    within = {0.0: [], -0.5: [], 0.5: []}
    for pair, matches in pairs_and_matches:
        if getattr(pair, "H", None) is None or not len(matches):
            continue
        k0, k1 = matches.keypoints0.astype(np.float64), matches.keypoints1.astype(np.float64)
        for shift, kept in within.items():
            error = np.linalg.norm(warp_points(pair.H, k0 + shift) - (k1 + shift), axis=1)
            kept.append(error <= CHECK_PX)
    if not within[0.0]:
        return None
    base = np.concatenate(within[0.0])
    best = None
    for shift in (-0.5, 0.5):
        moved = np.concatenate(within[shift])
        gained, lost = int(np.count_nonzero(moved & ~base)), int(np.count_nonzero(base & ~moved))
        z = (gained - lost) / np.sqrt(gained + lost) if gained + lost else 0.0
        check = HalfPixelCheck(len(base), float(base.mean()), float(moved.mean()), shift, float(z))
        if best is None or check.z > best.z:
            best = check
    return best
