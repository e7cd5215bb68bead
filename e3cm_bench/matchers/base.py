"""The matcher interface: two images in, matches in the images' pixels out."""

from __future__ import annotations

import numpy as np

from ..matches import Matches


class Matcher:
    """Base class. A matcher is one class with one method, ``match``.

    ``image0``/``image1`` are H x W x 3 uint8 RGB arrays. A matcher never reads files.
    ``config()`` returns every setting its result depends on (written to config.yaml).
    """

    name = "base"

    def match(self, image0: np.ndarray, image1: np.ndarray) -> Matches:  # pragma: no cover
        raise NotImplementedError

    def config(self) -> dict:
        return {"matcher": self.name}
