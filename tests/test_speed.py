"""The speed machinery changes no result: decoding ahead, cross-method feature sharing."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pytest

from e3cm_bench.datasets.base import Pair
from e3cm_bench.images import ImageError
from e3cm_bench.runner import decoded_ahead


def test_decoded_ahead_yields_each_pairs_images_and_its_own_error(tmp_path: Path):
    rng = np.random.default_rng(0)
    paths = []
    for i in range(3):
        path = tmp_path / f"{i}.png"
        cv2.imwrite(str(path), rng.integers(0, 255, (8 + i, 10, 3), dtype=np.uint8))
        paths.append(path)
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(b"\xff\xd8\xff not a whole jpeg")
    pairs = [Pair("a", paths[0], paths[1]), Pair("b", paths[1], bad), Pair("c", paths[2], paths[0])]
    seen = []
    with ThreadPoolExecutor(max_workers=1) as executor:
        for pair, images in decoded_ahead(pairs, executor):
            if pair.name == "b":
                with pytest.raises(ImageError, match="bad.jpg"):
                    images.result()
                continue
            image0, image1 = images.result()
            seen.append((pair.name, image0.shape[0], image1.shape[0]))
    assert seen == [("a", 8, 9), ("c", 10, 8)]
