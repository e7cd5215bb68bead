"""HPatches sequences: pairs (1, k), k = 2..6, with the ground-truth homography H_1_k."""

from __future__ import annotations

from collections.abc import Sequence
from fnmatch import fnmatch
from pathlib import Path

import numpy as np

from e3cm_bench.datasets.base import DatasetError, Pair, PairList, require_directory
from e3cm_bench.datasets.truth import check_homography

# D2-Net's protocol drops the sequences whose images exceed 1600 x 1200 (PROTOCOLS §2).
LARGE_SEQUENCES = (
    "i_contruction",
    "i_crownnight",
    "i_dc",
    "i_pencils",
    "i_whitebuilding",
    "v_artisans",
    "v_astronautis",
    "v_talent",
)
TARGET_IMAGES = range(2, 7)


class HPatches(PairList):
    """HPatches: ``root/{i_*,v_*}/{1..6}.ppm`` and ``H_1_k`` (image 1 pixels -> image k pixels).

    ``exclude_large`` gives the 108-sequence / 540-pair protocol; ``sequences`` keeps only
    the sequences matching any of the given names or fnmatch patterns.
    """

    name = "hpatches"

    def __init__(
        self,
        root: str | Path,
        exclude_large: bool = False,
        sequences: Sequence[str] | None = None,
        skip_bad: bool = False,
    ) -> None:
        self.root = require_directory(root, "HPatches")
        self.exclude_large = exclude_large
        if isinstance(sequences, str):  # one pattern given bare, not a list of its characters
            sequences = [sequences]
        self.sequence_patterns = list(sequences) if sequences is not None else None
        self.sequences = self._select_sequences()
        pairs, bad = [], []
        for sequence in self.sequences:
            for k in TARGET_IMAGES:
                try:
                    pairs.append(self._pair(sequence, k))
                except DatasetError as error:  # its H is missing or unusable
                    bad.append((f"{sequence}/1-{k}", str(error)))
        super().__init__(pairs, self.root, skip_bad, bad)

    def _select_sequences(self) -> list[str]:
        available = sorted(
            d.name for d in self.root.iterdir() if d.is_dir() and d.name[:2] in ("i_", "v_")
        )
        if self.sequence_patterns is not None:
            # A pattern that matches nothing is almost always a typo; say so instead of
            # quietly evaluating fewer sequences.
            for pattern in self.sequence_patterns:
                if not any(fnmatch(name, pattern) for name in available):
                    raise DatasetError(f"{self.root}: no sequence matches {pattern!r}")
            available = [n for n in available if any(fnmatch(n, p) for p in self.sequence_patterns)]
        if self.exclude_large:
            available = [n for n in available if n not in LARGE_SEQUENCES]
        return available

    def _pair(self, sequence: str, k: int) -> Pair:
        folder = self.root / sequence
        return Pair(
            name=f"{sequence}/1-{k}",
            image0=folder / "1.ppm",
            image1=folder / f"{k}.ppm",
            H=read_homography(folder / f"H_1_{k}"),
            sequence=sequence,
        )

    def settings(self) -> dict:
        if self.exclude_large:
            protocol = "108 sequences / 540 pairs (8 large sequences excluded)"
        else:
            protocol = "all 116 sequences / 580 pairs"
        return {
            "dataset": self.name,
            "root": str(self.root),
            "protocol": protocol,
            "sequence_filter": self.sequence_patterns,
            "n_sequences": len(self.sequences),
            "sequences": self.sequences,
        }


def read_homography(path: Path) -> np.ndarray:
    """A 3 x 3 whitespace-separated text matrix: finite and invertible (it maps image 1 to k)."""
    if not path.is_file():
        raise DatasetError(f"{path}: homography file not found")
    try:
        H = np.loadtxt(path, dtype=np.float64)
    except ValueError as error:
        reason = " ".join(str(error).split())  # keep the message on one line
        raise DatasetError(f"{path}: not a numeric matrix ({reason})") from None
    if H.shape != (3, 3):
        raise DatasetError(f"{path}: expected a 3x3 matrix, got shape {H.shape}")
    check_homography(H, str(path))
    return H
