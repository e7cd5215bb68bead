"""What every benchmark dataset yields: pairs of image paths with their ground truth."""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


class DatasetError(ValueError):
    """Bad or missing benchmark input; the message is one line naming the file and the problem."""


@dataclass
class Pair:
    """One image pair and its ground truth.

    ``name`` is unique within a dataset; it is the key of the pair in ``matches.h5`` and
    the ``pair`` column of ``per_pair.csv``. Homography pairs carry ``H`` (maps pixels of
    image 0 to image 1); pose pairs carry ``K0``, ``K1`` (original images) and ``T_0to1``
    (4x4, camera 0 to camera 1).
    """

    name: str
    image0: Path
    image1: Path
    H: np.ndarray | None = None
    K0: np.ndarray | None = None
    K1: np.ndarray | None = None
    T_0to1: np.ndarray | None = None
    meta: dict = field(default_factory=dict)  # e.g. {"sequence": "v_boat"}


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
