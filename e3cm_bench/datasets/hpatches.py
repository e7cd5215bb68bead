"""HPatches sequences: pairs (1, k), k = 2..6, with the ground-truth homography H_1_k.

Also home of ``PairList``, the small base shared by every dataset: a fixed list of pairs,
built once at construction, with the missing-image policy applied.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from fnmatch import fnmatch
from pathlib import Path

import numpy as np

from e3cm_bench.datasets.base import DatasetError, Pair

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


class PairList:
    """A dataset's pairs, checked for images on disk; iterable, sized, indexable.

    Subclasses build their pairs and pass them here with ``source``, the file or folder
    that the pairs came from (named in error messages). With ``skip_missing`` the pairs
    with a missing image are dropped and counted in ``n_skipped``; without it, any missing
    image is an error, so that a partial dataset never passes for the whole benchmark.
    """

    def __init__(self, pairs: Sequence[Pair], source: Path, skip_missing: bool) -> None:
        if not pairs:
            raise DatasetError(f"{source}: the pair list is empty")
        _reject_duplicate_names(pairs, source)
        missing = _missing_images(pairs)
        absent = set(missing)
        complete = [p for p in pairs if p.image0 not in absent and p.image1 not in absent]
        if missing and not skip_missing:
            examples = ", ".join(str(path) for path in missing[:3])
            raise DatasetError(
                f"{source}: {len(missing)} image(s) missing ({len(pairs) - len(complete)} of "
                f"{len(pairs)} pairs affected), e.g. {examples}; "
                "pass --skip-missing to evaluate only the pairs whose images exist"
            )
        self.pairs = complete
        self.n_skipped = len(pairs) - len(complete)
        self.skip_missing = skip_missing
        if not self.pairs:
            raise DatasetError(f"{source}: none of the {len(pairs)} pairs has both images on disk")

    def __iter__(self) -> Iterator[Pair]:
        return iter(self.pairs)

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, index: int) -> Pair:
        return self.pairs[index]

    def settings(self) -> dict:
        """What defines the pair list, besides its length (overridden by each dataset)."""
        return {}

    def describe(self) -> dict:
        return {
            **self.settings(),
            "skip_missing": self.skip_missing,
            "n_pairs": len(self.pairs),
            "n_skipped": self.n_skipped,
        }


def _reject_duplicate_names(pairs: Iterable[Pair], source: Path) -> None:
    # Names key the match cache and the per-pair CSV; a duplicate would silently overwrite.
    seen: set[str] = set()
    for pair in pairs:
        if pair.name in seen:
            raise DatasetError(f"{source}: pair name {pair.name!r} occurs twice")
        seen.add(pair.name)


def _missing_images(pairs: Iterable[Pair]) -> list[Path]:
    """Missing image paths, each once, in the order the pairs name them."""
    checked: dict[Path, bool] = {}
    for pair in pairs:
        for path in (pair.image0, pair.image1):
            if path not in checked:
                checked[path] = path.is_file()
    return [path for path, exists in checked.items() if not exists]


def require_directory(root: Path, what: str) -> Path:
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: {what} root folder not found")
    return root


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
        skip_missing: bool = False,
    ) -> None:
        self.root = require_directory(root, "HPatches")
        self.exclude_large = exclude_large
        if isinstance(sequences, str):  # one pattern given bare, not a list of its characters
            sequences = [sequences]
        self.sequence_patterns = list(sequences) if sequences is not None else None
        self.sequences = self._select_sequences()
        pairs = [self._pair(sequence, k) for sequence in self.sequences for k in TARGET_IMAGES]
        super().__init__(pairs, self.root, skip_missing)

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
            meta={"sequence": sequence, "split": sequence[0]},
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
    """A 3 x 3 whitespace-separated text matrix."""
    if not path.is_file():
        raise DatasetError(f"{path}: homography file not found")
    try:
        H = np.loadtxt(path, dtype=np.float64)
    except ValueError as error:
        reason = " ".join(str(error).split())  # keep the message on one line
        raise DatasetError(f"{path}: not a numeric matrix ({reason})") from None
    if H.shape != (3, 3) or not np.all(np.isfinite(H)):
        raise DatasetError(f"{path}: expected a finite 3x3 matrix, got shape {H.shape}")
    return H
