"""Images the package makes itself: procedural textures, the demo pair, and a real photograph.

`e3cm-bench match` with no images uses the demo pair (a procedural scene and a known
homography of it), so the tool runs with nothing to download. The real photograph is the
sample image that matplotlib ships (read from the installed package, never copied here).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

DEMO_SIZE = (640, 480)  # width, height


def procedural_scene(size: tuple[int, int] = DEMO_SIZE, seed: int = 0) -> np.ndarray:
    """An RGB image with structure at many scales (shapes, strokes, text and noise)."""
    w, h = size
    rng = np.random.default_rng(seed)
    # Multi-scale coloured noise as a background texture.
    image = np.zeros((h, w, 3), np.float32)
    for cells, weight in ((4, 0.5), (16, 0.3), (64, 0.2)):
        coarse = rng.random((cells * h // w + 1, cells, 3)).astype(np.float32)
        image += weight * cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
    image = np.clip(image * 255, 0, 255).astype(np.uint8)
    for _ in range(60):
        colour = tuple(int(c) for c in rng.integers(0, 256, 3))
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        kind = rng.integers(0, 4)
        if kind == 0:
            cv2.circle(image, (x, y), int(rng.integers(5, 40)), colour, -1, cv2.LINE_AA)
        elif kind == 1:
            cv2.rectangle(image, (x, y), (x + int(rng.integers(10, 80)), y + int(rng.integers(10, 80))), colour, -1)
        elif kind == 2:
            end = (int(rng.integers(0, w)), int(rng.integers(0, h)))
            cv2.line(image, (x, y), end, colour, int(rng.integers(1, 5)), cv2.LINE_AA)
        else:
            text = "".join(chr(c) for c in rng.integers(65, 91, 4))
            cv2.putText(
                image, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, float(rng.uniform(0.5, 1.5)), colour, 2, cv2.LINE_AA
            )
    return image


def demo_homography(size: tuple[int, int] = DEMO_SIZE) -> np.ndarray:
    """A moderate viewpoint change: rotation, scale and a little perspective about the centre."""
    w, h = size
    centre = np.array([[1, 0, -w / 2], [0, 1, -h / 2], [0, 0, 1]], dtype=np.float64)
    angle = np.deg2rad(12.0)
    scale = 0.9
    rotate = np.array(
        [
            [scale * np.cos(angle), -scale * np.sin(angle), 0],
            [scale * np.sin(angle), scale * np.cos(angle), 0],
            [0, 0, 1],
        ]
    )
    perspective = np.array([[1, 0, 0], [0, 1, 0], [1.5e-4, -1e-4, 1]])
    return np.linalg.inv(centre) @ perspective @ rotate @ centre


def demo_pair(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(image0, image1, H) with H mapping pixels of image0 to image1."""
    image0 = procedural_scene(seed=seed)
    H = demo_homography()
    image1 = cv2.warpPerspective(image0, H, DEMO_SIZE, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return image0, image1, H


PHOTO_NAME = "grace_hopper.jpg"  # in matplotlib's mpl-data/sample_data


def photo_path() -> Path:
    import matplotlib

    return Path(matplotlib.get_data_path()) / "sample_data" / PHOTO_NAME


def sample_photo() -> np.ndarray:
    """The real photograph shipped with matplotlib, H x W x 3 uint8 RGB (600 x 512)."""
    path = photo_path()
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise ValueError(f"{path}: matplotlib's sample photograph is missing (is matplotlib installed whole?)")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
