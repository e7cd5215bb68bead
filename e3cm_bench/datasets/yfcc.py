"""YFCC100M (and ScanNet sample) pair lists in the SuperGlue text format.

One pair a line: ``name0 name1 rot0 rot1 K0(9) K1(9) T_0to1(16)``, whitespace-separated.
rot0/rot1 are the EXIF quarter turns SuperGlue applies to make an image upright before
matching; the K and T_0to1 of the line describe the images as stored, so they stay valid
whatever the rotation. The rotations are passed on in ``Pair.rotations`` for a runner that wants
to match upright images (and map the matches back) and are otherwise unused.
"""

from __future__ import annotations

from pathlib import Path, PurePosixPath

import numpy as np

from e3cm_bench.datasets.base import DatasetError, Pair, PairList, require_directory, text_lines
from e3cm_bench.datasets.truth import check_intrinsics, check_pose

DEFAULT_PAIRS_FILE = "yfcc_test_pairs_with_gt.txt"
N_FIELDS = 2 + 2 + 9 + 9 + 16


class YFCC100M(PairList):
    """Pairs from ``root/yfcc_test_pairs_with_gt.txt`` or the ``pairs`` file given.

    An image name resolves to ``root/name`` when that exists, else ``root/images/name``
    (the layout of the ScanNet sample).
    """

    name = "yfcc"

    def __init__(
        self,
        root: str | Path,
        pairs: str | Path | None = None,
        skip_bad: bool = False,
    ) -> None:
        self.root = require_directory(root, "YFCC100M")
        self.pairs_file = Path(pairs) if pairs is not None else self.root / DEFAULT_PAIRS_FILE
        parsed, bad = self.read_pairs()
        super().__init__(parsed, self.pairs_file, skip_bad, bad)

    def read_pairs(self) -> tuple[list[Pair], list[tuple[str, str]]]:
        """The list's pairs, and (name, problem) of those whose K or T_0to1 is unusable; the
        PairList checks (names once, images present) are the caller's."""
        if not self.pairs_file.is_file():
            raise DatasetError(f"{self.pairs_file}: pair list not found")
        parsed, bad = [], []
        for number, line in text_lines(self.pairs_file, comments=False):  # bounded: a line, the file
            pair = self._parse_line(line, number)
            try:
                check_intrinsics(pair.K0, f"{self.pairs_file}:{number}: K0")
                check_intrinsics(pair.K1, f"{self.pairs_file}:{number}: K1")
                check_pose(pair.T_0to1, f"{self.pairs_file}:{number}: T_0to1")
            except DatasetError as error:
                bad.append((pair.name, str(error)))
                continue
            parsed.append(pair)
        return parsed, bad

    def _parse_line(self, line: str, number: int) -> Pair:
        where = f"{self.pairs_file}:{number}"
        fields = line.split()
        if len(fields) != N_FIELDS:
            raise DatasetError(f"{where}: expected {N_FIELDS} fields, found {len(fields)}")
        name0, name1 = fields[0], fields[1]
        try:
            rot0, rot1 = int(fields[2]), int(fields[3])
            values = np.array([float(v) for v in fields[4:]])
        except ValueError as error:
            raise DatasetError(f"{where}: not a number ({error})") from None
        if rot0 not in range(4) or rot1 not in range(4):
            raise DatasetError(
                f"{where}: EXIF rotations must be 0..3 quarter turns, got {rot0} {rot1}"
            )
        if not np.all(np.isfinite(values)):
            raise DatasetError(f"{where}: non-finite K or T_0to1")
        path0, path1 = PurePosixPath(name0), PurePosixPath(name1)
        stems = f"{path0.stem}--{path1.stem}"
        folder = str(path0.parent)
        return Pair(
            name=stems if folder == "." else f"{folder}/{stems}",
            image0=self._resolve(name0),
            image1=self._resolve(name1),
            K0=values[:9].reshape(3, 3),
            K1=values[9:18].reshape(3, 3),
            T_0to1=values[18:].reshape(4, 4),
            scene=path0.parts[0] if folder != "." else "", rotations=(rot0, rot1),
        )

    def _resolve(self, name: str) -> Path:
        direct = self.root / name
        if direct.is_file():
            return direct
        in_images = self.root / "images" / name
        # A name found nowhere keeps the direct path, which is what an error should report.
        return in_images if in_images.is_file() else direct

    def settings(self) -> dict:
        return {"dataset": self.name, "root": str(self.root), "pairs": str(self.pairs_file)}
