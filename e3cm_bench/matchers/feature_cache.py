"""Feature pyramids kept across the pairs of a run: in memory up to a budget, then on disk.

A benchmark's pairs share images (YFCC100M: 4000 pairs over 1455 images). The match stage
orders the pairs so that an image's pairs come close together (runner.reuse_order) and
tells the cache when an image has no pair left (`forget`); the cache keeps the pyramids of
the images still to be used:

- in memory, least recently used out first, up to `max_mb`;
- what memory cannot hold goes to a bounded folder on disk (`SpillStore`) and is read back
  when its image comes again, instead of passing it through the network again;
- maps computed in reduced precision are held in that precision (`compact_dtype`), where
  that is exact (checked, map by map), and handed back as float32.

Keyed by the image's content and channel order, and what is handed back is bit for bit what
the network computed, so the cache changes no result.
"""

from __future__ import annotations

import hashlib
import shutil
from collections import OrderedDict
from pathlib import Path

import numpy as np
import torch

# The default budget: this share of the memory available when the stage starts, at most the cap.
AUTO_SHARE = 0.5
AUTO_CAP_MB = 16384
# The default spill bound: this share of the free disk space of the run folder, at most the cap.
SPILL_SHARE = 0.5
SPILL_CAP_MB = 65536


def auto_cache_mb(device: torch.device | str = "cpu") -> float:
    """Half of the memory available now (the GPU's free memory for a CUDA device, the host's
    MemAvailable otherwise), at most 16 GiB; 2048 where nothing tells."""
    device = torch.device(device)
    if device.type == "cuda":
        free = torch.cuda.mem_get_info(device)[0]
    else:
        from ..devices import available_host_memory

        free = available_host_memory()
    if free is None:
        return 2048.0
    return float(min(AUTO_CAP_MB, AUTO_SHARE * free / 2**20))


def auto_spill_mb(folder: Path) -> float:
    """Half of the free disk space where the spill folder goes, at most 64 GiB."""
    folder = Path(folder)
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    return float(min(SPILL_CAP_MB, SPILL_SHARE * shutil.disk_usage(folder).free / 2**20))


def _nbytes(maps: list[torch.Tensor]) -> int:
    return sum(m.numel() * m.element_size() for m in maps)


def compact(maps: list[torch.Tensor], dtype: torch.dtype | None, exact: dict[int, bool] | None = None) -> list[torch.Tensor]:
    """Each float32 map in `dtype` where that holds it exactly (maps a reduced-precision
    network computed, then widened), else as it is. exact: level -> whether that level's maps
    are exact in dtype, filled by checking the first map of each level: a level's maps come
    out of the same layer in the same precision for every image, so one check tells."""
    if dtype is None:
        return maps
    exact = {} if exact is None else exact
    out = []
    for level, m in enumerate(maps):
        if m.dtype == torch.float32 and exact.get(level, True):
            narrow = m.to(dtype)
            if level not in exact:
                exact[level] = torch.equal(narrow.to(torch.float32), m)
            if exact[level]:
                m = narrow
        out.append(m)
    return out


def widen(maps: list[torch.Tensor]) -> list[torch.Tensor]:
    return [m if m.dtype == torch.float32 or not m.is_floating_point() else m.to(torch.float32) for m in maps]


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

    def _path(self, key: str) -> Path:
        return self.folder / (hashlib.blake2b(key.encode(), digest_size=16).hexdigest() + ".pt")

    def __contains__(self, key: str) -> bool:
        return key in self.sizes

    def write(self, key: str, maps: list[torch.Tensor]) -> bool:
        size = _nbytes(maps)
        if self.bytes + size > self.max_bytes:
            self.refused += 1
            return False
        self.folder.mkdir(parents=True, exist_ok=True)
        torch.save([m.cpu() for m in maps], self._path(key))
        self.sizes[key] = size
        self.bytes += size
        self.peak_bytes = max(self.peak_bytes, self.bytes)
        self.writes += 1
        return True

    def read(self, key: str, device: torch.device | str) -> list[torch.Tensor]:
        """The maps written under key (the file is removed: they go back to memory)."""
        path = self._path(key)
        maps = torch.load(path, map_location=device, weights_only=True)
        self.remove(key)
        self.reads += 1
        return maps

    def remove(self, key: str) -> None:
        size = self.sizes.pop(key, None)
        if size is not None:
            self.bytes -= size
            self._path(key).unlink(missing_ok=True)

    def close(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)
        self.sizes.clear()
        self.bytes = 0


class FeatureCache:
    """The feature pyramids of the images of a run, up to a memory budget (least recently used
    out first, to `spill` when there is one). hits: pyramids served without a backbone pass
    (from memory or disk); misses: backbone passes."""

    def __init__(self, max_mb: float, spill: SpillStore | None = None, compact_dtype: torch.dtype | None = None):
        self.max_bytes = int(max_mb * 2**20)
        self.spill = spill
        self.compact_dtype = compact_dtype
        self.exact_levels: dict[int, bool] = {}  # filled by compact
        self.entries: OrderedDict[str, list[torch.Tensor]] = OrderedDict()
        self.bytes = 0
        self.peak_bytes = 0
        self.hits = 0
        self.misses = 0
        self.seen: set[str] = set()
        # The files of the pair being matched (set by the match stage), and which file's maps
        # each key holds: a key is forgotten once every file it belongs to has no pair left.
        self.pair_files: tuple[str, str] | None = None
        self.keys_of: dict[str, set[str]] = {}
        self.files_of: dict[str, set[str]] = {}

    @staticmethod
    def key(image: np.ndarray, channel_order: str) -> str:
        digest = hashlib.blake2b(np.ascontiguousarray(image).data, digest_size=16)
        return f"{image.shape}:{image.dtype}:{channel_order}:{digest.hexdigest()}"

    def get(self, key: str, device: torch.device | str = "cpu") -> list[torch.Tensor] | None:
        self.seen.add(key)
        maps = self.entries.get(key)
        if maps is not None:
            self.entries.move_to_end(key)
            self.hits += 1
            return widen(maps)
        if self.spill is not None and key in self.spill:
            maps = self.spill.read(key, device)
            self._hold(key, maps)
            self.hits += 1
            return widen(maps)
        self.misses += 1
        return None

    def put(self, key: str, maps: list[torch.Tensor]) -> None:
        self.seen.add(key)
        self._hold(key, compact(maps, self.compact_dtype, self.exact_levels))

    def _hold(self, key: str, maps: list[torch.Tensor]) -> None:
        size = _nbytes(maps)
        if size > self.max_bytes:
            if self.spill is not None:
                self.spill.write(key, maps)
            return
        self.entries[key] = maps
        self.bytes += size
        while self.bytes > self.max_bytes:
            old_key, old = self.entries.popitem(last=False)
            self.bytes -= _nbytes(old)
            if self.spill is not None:
                self.spill.write(old_key, old)
        self.peak_bytes = max(self.peak_bytes, self.bytes)

    def belongs_to(self, key: str, which: int | None) -> None:
        """Record that key holds the maps of file `which` (0 or 1) of the pair being matched."""
        if self.pair_files is None or which is None:
            return
        file = self.pair_files[which]
        self.keys_of.setdefault(file, set()).add(key)
        self.files_of.setdefault(key, set()).add(file)

    def done_with(self, file: str) -> None:
        """The file has no pair left: the maps that belong to it alone leave memory and disk."""
        for key in self.keys_of.pop(file, ()):
            files = self.files_of.get(key, set())
            files.discard(file)
            if not files:
                self.files_of.pop(key, None)
                self.forget(key)

    def forget(self, key: str) -> None:
        maps = self.entries.pop(key, None)
        if maps is not None:
            self.bytes -= _nbytes(maps)
        if self.spill is not None:
            self.spill.remove(key)

    def stats(self) -> dict:
        """The counts `config.yaml: feature_reuse` records (passes per distinct image, etc.)."""
        distinct = len(self.seen)
        out = {"distinct_images": distinct, "backbone_passes": self.misses, "reused": self.hits,
               "passes_per_image": round(self.misses / distinct, 4) if distinct else 0.0,
               "peak_memory_mb": round(self.peak_bytes / 2**20, 1)}
        if self.spill is not None:
            out.update(read_from_disk=self.spill.reads, written_to_disk=self.spill.writes,
                       peak_disk_mb=round(self.spill.peak_bytes / 2**20, 1), disk_full=self.spill.refused)
        return out

    def close(self) -> None:
        """Drop every pyramid held (memory and disk)."""
        self.entries.clear()
        self.bytes = 0
        if self.spill is not None:
            self.spill.close()
