"""Match drawings: two images side by side with one line per correspondence."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from e3cm_bench.ground.matches import Matches, distinct


GREEN = (0, 255, 0)  # RGB: the canvas is RGB, and cv2 drawing just writes channel values
RED = (255, 0, 0)
BANNER_TEXT = (255, 255, 255)
BANNER_BACKGROUND = (0, 0, 0)
SUBPIXEL_BITS = 4  # cv2 drawing "shift": endpoints at 1/16 pixel instead of rounded
VIZ_SEED = 0  # the drawn pairs are the same in every run of a dataset, so drawings can be compared


def drawn(matches: Matches) -> Matches:
    """The matches a drawing shows: the ones the evaluation scored (each correspondence once),
    so that the drawing's count is the row's n_matches."""
    return distinct(matches)[0]


def drawn_pairs(pairs: list, n: int) -> list:
    """The `n` pairs that --viz draws: a spread over the run's categories, scenes or sequences
    (datasets.base.stratified_sample with a fixed seed), not the first n, which in a dataset
    sorted by sequence are all of one kind (HPatches' first pairs are all illumination)."""
    from e3cm_bench.datasets.base import stratified_sample

    return stratified_sample(pairs, n, VIZ_SEED) if n > 0 else []


def draw_matches(
    image0: np.ndarray,
    image1: np.ndarray,
    kpts0: np.ndarray,
    kpts1: np.ndarray,
    correct: np.ndarray | None = None,
    max_lines: int | None = None,
    seed: int = 0,
) -> np.ndarray:
    """RGB uint8 canvas of height max(h0, h1) and width w0 + w1 with the matches drawn.

    Lines are green for ``correct[i]`` True and red for False; without ``correct`` each
    line takes a colour from the turbo colormap by the height of its point in image 0,
    so neighbouring matches share a hue and a crossing outlier stands out. At most
    ``max_lines`` matches are drawn, a seeded random subset; the banner counts all.
    """
    kpts0 = np.asarray(kpts0, dtype=np.float64).reshape(-1, 2)
    kpts1 = np.asarray(kpts1, dtype=np.float64).reshape(-1, 2)
    if len(kpts0) != len(kpts1):
        raise ValueError(f"kpts0 and kpts1 differ in length: {len(kpts0)} vs {len(kpts1)}")
    if correct is not None:
        correct = np.asarray(correct, dtype=bool).reshape(-1)
        if len(correct) != len(kpts0):
            raise ValueError(f"correct has {len(correct)} entries for {len(kpts0)} matches")

    image0, image1 = _as_rgb(image0), _as_rgb(image1)
    (h0, w0), (h1, w1) = image0.shape[:2], image1.shape[:2]
    canvas = np.zeros((max(h0, h1), w0 + w1, 3), dtype=np.uint8)  # black pads the shorter image
    canvas[:h0, :w0] = image0
    canvas[:h1, w0:] = image1

    colours = _line_colours(kpts0, h0, correct)
    drawn = np.arange(len(kpts0))
    if max_lines is not None and len(drawn) > max_lines:
        rng = np.random.default_rng(seed)
        drawn = np.sort(rng.choice(len(drawn), size=max_lines, replace=False))

    scale = 1 << SUBPIXEL_BITS
    for i in drawn:
        start = tuple(int(v) for v in np.round(kpts0[i] * scale))
        end = tuple(int(v) for v in np.round((kpts1[i] + (w0, 0)) * scale))
        colour = colours[i]
        cv2.line(canvas, start, end, colour, 1, cv2.LINE_AA, SUBPIXEL_BITS)
        cv2.circle(canvas, start, 2 * scale, colour, 1, cv2.LINE_AA, SUBPIXEL_BITS)
        cv2.circle(canvas, end, 2 * scale, colour, 1, cv2.LINE_AA, SUBPIXEL_BITS)

    _draw_banner(canvas, _banner_text(len(kpts0), len(drawn), correct))
    return canvas


def save_image(path: str | Path, rgb: np.ndarray, params: list[int] | None = None) -> Path:
    """Write an RGB image (format from the extension; params: cv2.imwrite's, e.g. JPEG quality),
    creating parent folders. Encoded in memory and written by write_atomically: cv2.imwrite
    would open the name following a link at it."""
    from e3cm_bench.ground.files import write_atomically

    path = Path(path)
    try:
        ok, encoded = cv2.imencode(path.suffix, cv2.cvtColor(_as_rgb(rgb), cv2.COLOR_RGB2BGR), params or [])
    except cv2.error:
        ok = False
    if not ok:
        raise ValueError(f"cannot write image {path} (unknown extension {path.suffix!r})")
    return write_atomically(path, lambda tmp: tmp.write_bytes(encoded.tobytes()))


def _as_rgb(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise ValueError(f"expected a uint8 image, got {image.dtype}")
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    return image


def _line_colours(kpts0: np.ndarray, height0: int, correct: np.ndarray | None) -> list[tuple[int, int, int]]:
    if correct is not None:
        return [GREEN if ok else RED for ok in correct]
    if len(kpts0) == 0:
        return []
    levels = np.clip(kpts0[:, 1] / max(height0 - 1, 1) * 255, 0, 255).astype(np.uint8)
    bgr = cv2.applyColorMap(levels.reshape(-1, 1), cv2.COLORMAP_TURBO).reshape(-1, 3)
    return [(int(r), int(g), int(b)) for b, g, r in bgr]


def _banner_text(n_matches: int, n_drawn: int, correct: np.ndarray | None) -> str:
    text = f"{n_matches} matches"
    if correct is not None:
        text += f", correct: {int(correct.sum())}/{n_matches}"
    if n_drawn < n_matches:
        text += f" ({n_drawn} drawn)"
    return text


def _draw_banner(canvas: np.ndarray, text: str) -> None:
    # Text grows with the canvas so it stays legible on megapixel pairs.
    font_scale = max(0.5, canvas.shape[0] / 800)
    thickness = max(1, round(font_scale))
    font = cv2.FONT_HERSHEY_SIMPLEX
    (text_w, text_h), baseline = cv2.getTextSize(text, font, font_scale, thickness)
    margin = max(4, text_h // 3)
    cv2.rectangle(canvas, (0, 0), (text_w + 2 * margin, text_h + baseline + 2 * margin), BANNER_BACKGROUND, -1)
    cv2.putText(canvas, text, (margin, margin + text_h), font, font_scale, BANNER_TEXT, thickness, cv2.LINE_AA)
