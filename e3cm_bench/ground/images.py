"""Image loading and resizing, with the coordinate mapping back to original pixels.

Matchers see RGB uint8 arrays, often shrunk so the longer side fits a budget; metrics
need keypoints in the original image. Coordinates are pixel-centre (the centre of the
top-left pixel is (0, 0)), so a resize by s maps x to (x + 0.5) * s - 0.5, not x * s:
pixel edges, not pixel centres, scale linearly.
"""

from __future__ import annotations

import os
import re
import threading
from pathlib import Path

import cv2
import numpy as np


# Binary PGM/PPM header: magic, width, height, maxval (comments allowed), one whitespace byte.
_PNM_HEADER = re.compile(
    rb"P[56](?:\s+(?:#[^\n]*\n\s*)*(\d+)){1}(?:\s+(?:#[^\n]*\n\s*)*(\d+))(?:\s+(?:#[^\n]*\n\s*)*(\d+))\s"
)


def image_file_problem(path: str | Path) -> str | None:
    """What is wrong with an image file that reading a few bytes can tell, or None.

    Missing, empty, or cut short: OpenCV decodes a truncated JPEG without an error (the
    missing rows come out gray), so JPEG files must end with the EOI marker, PNG files with
    the IEND chunk, and binary PNM files must hold the pixels their header announces.
    """
    path = Path(path)
    if not path.is_file():
        return "image file not found"
    size = path.stat().st_size
    if size == 0:
        return "image file is empty"
    with open(path, "rb") as f:
        head = f.read(64)
        f.seek(max(0, size - 16))
        tail = f.read()
    if head[:3] == b"\xff\xd8\xff" and b"\xff\xd9" not in tail:
        return "JPEG file is cut short (no end-of-image marker)"
    if head[:8] == b"\x89PNG\r\n\x1a\n" and b"IEND" not in tail:
        return "PNG file is cut short (no IEND chunk)"
    if head[:2] in (b"P5", b"P6"):
        header = _PNM_HEADER.match(head)
        if header is None:
            return "PNM header is unreadable"
        width, height, maxval = (int(v) for v in header.groups())
        channels = 3 if head[:2] == b"P6" else 1
        expected = header.end() + width * height * channels * (2 if maxval > 255 else 1)
        if size < expected:
            return f"PNM file is cut short ({size} bytes, its header announces {expected})"
    return None


class ImageError(ValueError):
    """An image that cannot be used; the message names the file and the problem."""


MAX_PIXELS = 100_000_000  # the largest image decoded (3 bytes a pixel); E3CM_BENCH_MAX_PIXELS raises it
MAX_PIXELS_VARIABLE = "E3CM_BENCH_MAX_PIXELS"
_PIL_BOUND = threading.Lock()


def max_pixels() -> int:
    value = os.environ.get(MAX_PIXELS_VARIABLE)
    if not value:
        return MAX_PIXELS
    try:
        bound = int(value)
    except ValueError:
        raise ImageError(f"{MAX_PIXELS_VARIABLE}={value!r} is not a whole number of pixels") from None
    if bound < 1:
        raise ImageError(f"{MAX_PIXELS_VARIABLE}={value!r} must be positive")
    return bound


def header_size(path: str | Path) -> tuple[int, int] | None:
    """(w, h) from an image file's header, without decoding it; None where PIL cannot tell
    (a format it does not know, a damaged file, a header over PIL's own pixel bound)."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:
            return image.size
    except (UnidentifiedImageError, Image.DecompressionBombError, OSError, ValueError):
        return None


def check_pixel_count(path: str | Path) -> None:
    """ImageError when the header announces more pixels than max_pixels(), read before any
    decoding: a small file can hold a huge image (a 389 KB PNG of 20000 x 20000 decodes into
    1.2 GB, and every copy after). Formats PIL does not know are left to OpenCV."""
    from PIL import Image, UnidentifiedImageError

    bound = max_pixels()
    with _PIL_BOUND:  # PIL's own bound (a process-wide setting) is this one's to enforce, here
        previous, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None
        try:
            with Image.open(path) as image:
                width, height = image.size
        except (UnidentifiedImageError, OSError, ValueError):
            return
        finally:
            Image.MAX_IMAGE_PIXELS = previous
    if width * height > bound:
        size = f"{width} x {height} ({width * height / 1e6:.0f} megapixels)"
        raise ImageError(
            f"{path}: {size}, over the bound of {bound / 1e6:g} megapixels an image is decoded at "
            f"(it is decoded whole before --max-side shrinks it); set {MAX_PIXELS_VARIABLE}=N to raise the bound"
        )


def load_image(path: str | Path) -> np.ndarray:
    """H x W x 3 uint8 RGB; grayscale files are replicated to three channels."""
    # Checked first: OpenCV would print its own warning for a missing file before our error,
    # and would decode a truncated file without any.
    problem = image_file_problem(path)
    if problem:
        raise ImageError(f"{path}: {problem}")
    check_pixel_count(path)
    # IMREAD_COLOR always yields 3 channels: gray is replicated, alpha dropped, 16-bit scaled.
    # OpenCV's own log lines about a broken file would precede our one-line error: silenced.
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    finally:
        cv2.utils.logging.setLogLevel(level)
    if image is None:
        raise ImageError(f"{path}: cannot read the image (unreadable or not an image)")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


# How images are brought to `max_side` (MethodSpec.resize; the pose protocols set it):
#   shrink: ours: longer side at most max_side, area averaging, never enlarged;
#   exact: longer side exactly max_side, enlarged too, bilinear (SuperGlue's process_resize,
#     `match_pairs.py --resize N`);
#   exact-div8: as exact, then each side floored to a multiple of 8 (LoFTR's get_resized_wh
#     and get_divisible_wh with df = 8, its MegaDepth-1500 test loader).
RESIZE_MODES = ("shrink", "exact", "exact-div8")


def resize_max_side(
    image: np.ndarray, max_side: int | None, how: str = "shrink"
) -> tuple[np.ndarray, tuple[float, float]]:
    """Resize by the longer side (`how`: one of RESIZE_MODES, above).

    Returns the image and ``scale_xy = (w / w', h / h')`` (original over resized size,
    per axis, since rounding makes the two differ slightly). ``max_side`` None or 0
    means no resize.
    """
    if max_side is not None and max_side < 0:
        raise ValueError(f"max_side must be positive, 0 or None, got {max_side}")
    if how not in RESIZE_MODES:
        raise ValueError(f"unknown resize {how!r}; choose one of {', '.join(RESIZE_MODES)}")
    height, width = image.shape[:2]
    if not max_side or (how == "shrink" and max(height, width) <= max_side):
        return image, (1.0, 1.0)
    factor = max_side / max(height, width)
    new_width = max(1, round(width * factor))
    new_height = max(1, round(height * factor))
    if how == "shrink":
        # Area averaging avoids the aliasing that bilinear sampling shows when shrinking.
        resized = cv2.resize(image, (new_width, new_height), interpolation=cv2.INTER_AREA)
        return resized, (width / new_width, height / new_height)
    if how == "exact-div8":
        new_width, new_height = max(8, new_width // 8 * 8), max(8, new_height // 8 * 8)
    if (new_width, new_height) == (width, height):
        return image, (1.0, 1.0)
    # The references call cv2.resize with its default, bilinear interpolation.
    resized = cv2.resize(image, (new_width, new_height), interpolation=cv2.INTER_LINEAR)
    return resized, (width / new_width, height / new_height)


def to_original_pixels(kpts: np.ndarray, scale_xy: tuple[float, float]) -> np.ndarray:
    """Pixel-centre coordinates in the resized image -> the same in the original, N x 2 float32."""
    kpts = np.asarray(kpts, dtype=np.float64).reshape(-1, 2)
    scale = np.asarray(scale_xy, dtype=np.float64).reshape(1, 2)
    return ((kpts + 0.5) * scale - 0.5).astype(np.float32)
