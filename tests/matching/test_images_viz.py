"""Image loading/resizing with the pixel-centre mapping back, and the match drawings."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from e3cm_bench.ground.images import load_image, resize_max_side, to_original_pixels
from e3cm_bench.drawing.matches import draw_matches, save_image



def is_green(pixels: np.ndarray) -> np.ndarray:
    # Anti-aliased lines blend a little background in, so classify rather than compare exactly.
    r, g, b = np.moveaxis(np.asarray(pixels, dtype=int), -1, 0)
    return (g > 200) & (r < 80) & (b < 80)


def is_red(pixels: np.ndarray) -> np.ndarray:
    r, g, b = np.moveaxis(np.asarray(pixels, dtype=int), -1, 0)
    return (r > 200) & (g < 80) & (b < 80)


# ------------------------------------------------------------------ resizing


def test_resize_scale_and_mapping_back_by_hand():
    image = np.zeros((600, 1000, 3), np.uint8)
    resized, scale_xy = resize_max_side(image, 500)
    assert resized.shape == (300, 500, 3)
    assert scale_xy == (2.0, 2.0)
    # Resized pixel 0 covers original pixels 0 and 1, whose centres average to 0.5;
    # resized pixel 499 covers 998 and 999 -> 998.5; the left image edge (-0.5) stays put.
    back = to_original_pixels(np.array([[0.0, 0.0], [499.0, 299.0], [-0.5, -0.5]]), scale_xy)
    np.testing.assert_allclose(back, [[0.5, 0.5], [998.5, 598.5], [-0.5, -0.5]])
    assert back.dtype == np.float32


def test_resize_rounding_gives_per_axis_scales():
    resized, (sx, sy) = resize_max_side(np.zeros((601, 1001, 3), np.uint8), 500)
    # 601 * 500 / 1001 = 300.2 -> 300 rows, so the two axes scale differently.
    assert resized.shape[:2] == (300, 500)
    assert sx == pytest.approx(1001 / 500) and sy == pytest.approx(601 / 300)
    # The last resized pixel's right edge (499.5) maps onto the original right edge (1000.5).
    np.testing.assert_allclose(to_original_pixels([[499.5, 299.5]], (sx, sy)), [[1000.5, 600.5]], rtol=1e-6)


def test_mapping_agrees_with_what_area_resize_does():
    image = np.zeros((40, 60, 3), np.uint8)
    image[20:22, 10:12] = 255  # a 2 x 2 block whose centre is (x, y) = (10.5, 20.5)
    resized, scale_xy = resize_max_side(image, 30)
    ys, xs = np.nonzero(resized[..., 0])
    assert (xs.tolist(), ys.tolist()) == ([5], [10])
    np.testing.assert_allclose(to_original_pixels([[5, 10]], scale_xy), [[10.5, 20.5]])


def test_no_resize_and_no_upscale():
    image = np.zeros((120, 80, 3), np.uint8)
    for max_side in (None, 0, 120, 4000):
        resized, scale_xy = resize_max_side(image, max_side)
        assert resized is image and scale_xy == (1.0, 1.0)
    with pytest.raises(ValueError):
        resize_max_side(image, -5)


# ------------------------------------------------------------------- loading


def test_load_grayscale_png_gives_three_channels(tmp_path):
    gray = np.tile(np.arange(64, dtype=np.uint8), (32, 1))
    cv2.imwrite(str(tmp_path / "gray.png"), gray)
    image = load_image(tmp_path / "gray.png")
    assert image.shape == (32, 64, 3) and image.dtype == np.uint8
    for channel in range(3):
        np.testing.assert_array_equal(image[..., channel], gray)


def test_load_and_save_keep_rgb_order(tmp_path):
    rgb = np.zeros((8, 8, 3), np.uint8)
    rgb[..., 0] = 200  # red only
    path = save_image(tmp_path / "deep" / "folder" / "red.png", rgb)
    assert path.is_file()
    np.testing.assert_array_equal(load_image(path), rgb)


def test_unreadable_image_names_the_file(tmp_path):
    broken = tmp_path / "broken.png"
    broken.write_text("not an image")
    for path in (broken, tmp_path / "missing.jpg"):
        with pytest.raises(ValueError, match=str(path.name)):
            load_image(path)


# ------------------------------------------------------------------- drawing


def two_images():
    image0 = np.full((100, 200, 3), 50, np.uint8)
    image1 = np.full((150, 120, 3), 100, np.uint8)
    return image0, image1


def test_canvas_shape_and_padding():
    image0, image1 = two_images()
    canvas = draw_matches(image0, image1, np.zeros((0, 2)), np.zeros((0, 2)))
    assert canvas.shape == (150, 320, 3) and canvas.dtype == np.uint8
    assert (canvas[60, 10] == 50).all() and (canvas[60, 250] == 100).all()
    assert (canvas[120:, :200] == 0).all()  # the shorter image is padded with black
    assert (canvas[:10, :10] == 255).any()  # the banner text


def test_correct_matches_green_and_wrong_red():
    image0, image1 = two_images()
    kpts0 = np.array([[50.0, 80.0], [50.0, 95.0]])
    kpts1 = np.array([[60.0, 80.0], [60.0, 95.0]])  # horizontal lines at rows 80 and 95
    canvas = draw_matches(image0, image1, kpts0, kpts1, correct=[True, False])
    # Midway along each line (canvas x = 150).
    assert is_green(canvas[80, 150]) and not is_red(canvas[80, 150])
    assert is_red(canvas[95, 150]) and not is_green(canvas[95, 150])
    assert tuple(canvas[88, 150]) == (50, 50, 50)  # untouched between the lines
    # The line ends on the match in image 1, shifted by the width of image 0.
    assert is_green(canvas[80, 200 + 58])
    assert not is_green(canvas[80, 200 + 66 :]).any()
    assert is_green(canvas).sum() > 100 and is_red(canvas).sum() > 100


def test_without_correctness_lines_are_coloured_but_not_judged():
    image0, image1 = two_images()
    kpts0 = np.array([[50.0, 40.0], [50.0, 90.0]])
    canvas = draw_matches(image0, image1, kpts0, kpts0 + (10, 0))
    top, bottom = tuple(canvas[40, 150]), tuple(canvas[90, 150])
    assert top != (50, 50, 50) and bottom != (50, 50, 50)
    assert top != bottom  # colour follows the height in image 0


def test_max_lines_draws_a_seeded_subset():
    image0, image1 = two_images()
    rows = np.arange(30, 100, 7, dtype=float)  # 10 horizontal matches
    kpts0 = np.stack([np.full_like(rows, 50), rows], axis=1)
    kpts1 = kpts0 + (10, 0)

    def drawn_rows(seed):
        canvas = draw_matches(image0, image1, kpts0, kpts1, correct=np.ones(10, bool), max_lines=3, seed=seed)
        return [int(r) for r in rows if is_green(canvas[int(r), 150])]

    assert len(drawn_rows(0)) == 3
    assert drawn_rows(0) == drawn_rows(0)
    assert len({tuple(drawn_rows(seed)) for seed in range(5)}) > 1


def test_mismatched_inputs_raise():
    image0, image1 = two_images()
    with pytest.raises(ValueError):
        draw_matches(image0, image1, np.zeros((3, 2)), np.zeros((2, 2)))
    with pytest.raises(ValueError):
        draw_matches(image0, image1, np.zeros((2, 2)), np.zeros((2, 2)), correct=[True])
