"""The feature cache's disk tier: pyramids (or a two-stage matcher's features) that memory cannot
hold, one file each in a folder of the run's, up to a bound (matchers/feature_cache.py decides
what goes there and when; this module only keeps files within the bound and reads them back
as they were written)."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path
from typing import TYPE_CHECKING

from e3cm_bench.ground.files import refuse_link
from e3cm_bench.ground.folders import fresh_folder, remove_folder
from e3cm_bench.matchers.feature_values import from_portable, nbytes as _nbytes, portable

if TYPE_CHECKING:
    import torch

# The default spill bound: this share of the free disk space of the run folder, at most the cap.
SPILL_SHARE = 0.5
SPILL_CAP_MB = 65536


def auto_spill_mb(folder: Path) -> float:
    """Half of the free disk space where the spill folder goes, at most 64 GiB."""
    folder = Path(folder)
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    return float(min(SPILL_CAP_MB, SPILL_SHARE * shutil.disk_usage(folder).free / 2**20))


class SpillStore:
    """Pyramids on disk, one file each, up to `max_mb`: a write that would pass the bound is
    refused (the image is then passed through the network again when it comes back). The
    folder is the store's own: `close` removes it."""

    def __init__(self, folder: Path, max_mb: float):
        self.folder = Path(folder)
        self.max_bytes = int(max_mb * 2**20)
        self.sizes: dict[str, int] = {}
        self.bytes = 0
        self.peak_bytes = 0
        self.writes = 0
        self.reads = 0
        self.refused = 0
        self.dropped = 0  # removed to make room for a pyramid needed sooner
        self.made = None  # the folder, once the first write has made it

    def _path(self, key: str) -> Path:
        return self.folder / (hashlib.blake2b(key.encode(), digest_size=16).hexdigest() + ".pt")

    def __contains__(self, key: str) -> bool:
        return key in self.sizes

    def write(self, key: str, maps: list[torch.Tensor]) -> bool:
        import torch

        size, packed = _nbytes(maps), portable(maps)
        if self.bytes + size > self.max_bytes or packed is None:  # None: features that cannot go to disk
            self.refused += 1
            return False
        if not self.made:  # made anew, never through a link at it or at its parent (the stage's spill folder)
            self.made = fresh_folder(refuse_link(self.folder.parent) / self.folder.name)
        torch.save(packed, self._path(key))
        self.sizes[key] = size
        self.bytes += size
        self.peak_bytes = max(self.peak_bytes, self.bytes)
        self.writes += 1
        return True

    def read(self, key: str, device: torch.device | str, keep: bool = False) -> list[torch.Tensor]:
        """The maps written under key; the file is removed (they go back to memory) unless keep."""
        import torch

        path = self._path(key)
        maps = from_portable(torch.load(path, map_location=device, weights_only=True))
        if not keep:
            self.remove(key)
        self.reads += 1
        return maps

    def remove(self, key: str) -> None:
        size = self.sizes.pop(key, None)
        if size is not None:
            self.bytes -= size
            self._path(key).unlink(missing_ok=True)

    def close(self) -> None:
        remove_folder(refuse_link(self.folder.parent) / self.folder.name, ignore_errors=True)  # never through a link
        self.made = None
        self.sizes.clear()
        self.bytes = 0
