"""Feature pyramids kept across the pairs of a run: in memory up to a budget, then on disk.

A benchmark's pairs share images (YFCC100M: 4000 pairs over 1455 images). The match stage
orders the pairs so that few images are alive at once (pair_order.reuse_order), tells the
cache that order (`plan`) and, after each pair, which images have no pair left
(`done_with`); the cache keeps the pyramids of the images still to be used:

- in memory up to `max_mb`; when it is full, out goes the pyramid needed again last
  (Belady's rule: with the order known it needs the fewest passes; least recently used
  when no order was given);
- what memory cannot hold goes to a bounded folder on disk (`SpillStore`, matchers/spill.py) and is read back
  when its image comes again, instead of passing it through the network again; when the
  disk bound is reached, the pyramid needed last is the one left to be computed again;
- maps computed in reduced precision are held in that precision (`compact_dtype`), where
  that is exact (checked, map by map), and handed back as float32;
- what a matcher computes from one image's maps alone (a level normalised; the float32 copy
  of maps held in bf16), or keeps from its pass (level 0's channels-last rows), is kept
  beside them (`derived`), within the same budget, and is the first thing to go when
  memory is short: it is made again from the maps in a fraction of a pass.

Keyed by the image's content and channel order, and what is handed back is bit for bit what
the network computed, so the cache changes no result.

The same cache holds a two-stage matcher's `Features` (matchers/two_stage.py), keyed by the
image's content and the matcher's identity: one extraction per image of a run. torch is
imported where a pyramid or a file needs it, so a classical matcher's run goes without it.
"""

from __future__ import annotations

import hashlib
import math
from bisect import bisect_left
from collections import OrderedDict
from typing import TYPE_CHECKING

import numpy as np

from e3cm_bench.matchers.feature_values import compact, nbytes as _nbytes, widen

if TYPE_CHECKING:
    import torch

from e3cm_bench.ground.moved import moved_name
from e3cm_bench.matchers.spill import SpillStore

# The default budget: this share of the memory available when the stage starts, at most the cap.
AUTO_SHARE = 0.5
AUTO_CAP_MB = 16384


def auto_cache_mb(device: torch.device | str = "cpu") -> float:
    """Half of the memory available now (the GPU's free memory for a CUDA device, the host's
    MemAvailable otherwise), at most 16 GiB; 2048 where nothing tells."""
    if str(device).startswith("cuda"):
        import torch

        free = torch.cuda.mem_get_info(torch.device(device))[0]
    else:
        from e3cm_bench.ground.devices import available_host_memory

        free = available_host_memory()
    if free is None:
        return 2048.0
    return float(min(AUTO_CAP_MB, AUTO_SHARE * free / 2**20))


class FeatureCache:
    """The feature pyramids of the images of a run, up to a memory budget (what is needed again
    last goes out first, to `spill` when there is one; see the module). hits: pyramids served
    without a backbone pass (from memory or disk); misses: backbone passes."""

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
        # The stage's order (plan): the pairs, by position, each file is in; the position now.
        self.uses: dict[str, list[int]] | None = None
        self.position = -1
        self.claim: int | None = None  # the file of the pair whose maps are asked for (belongs_to)
        self.served: set[tuple[str, int]] = set()  # (key, file of the pair) handed out for this pair
        # Products of a key's maps (derived), by key and name, and their bytes per key.
        self.products: dict[str, dict[str, object]] = {}
        self.product_bytes: dict[str, int] = {}
        self.products_reused = 0

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
            self._serve(key)
            return self._wide(key, maps)
        if self.spill is not None and key in self.spill:
            stays = self.spill.sizes[key] > self.max_bytes  # memory cannot hold it: read, not moved
            maps = self.spill.read(key, device, keep=stays)
            self._serve(key)
            if not stays:
                self._hold(key, maps)
            self.hits += 1
            return self._wide(key, maps)
        self.misses += 1
        return None

    def _wide(self, key: str, maps: list[torch.Tensor]) -> list[torch.Tensor]:
        """The maps as float32: those held narrow are widened once and the copy kept (derived)."""
        if not isinstance(maps, list):  # a two-stage matcher's Features: held as computed
            return maps
        import torch  # a pyramid: its maps are tensors

        if all(m.dtype == torch.float32 or not m.is_floating_point() for m in maps):
            return maps
        return self.derived(key, "float32", lambda: widen(maps))

    def derived(self, key: str, name: str, compute):
        """compute(): something made from key's maps alone (e.g. a level normalised), named so
        that the name says how. Kept beside the maps while they are held in memory, if it fits
        in the budget once the products of images needed later are dropped (never maps for
        it); the same object is handed back while it is kept."""
        held = self.products.get(key)
        if held is not None and name in held:
            self.products_reused += 1
            return held[name]
        value = compute()
        if key in self.entries:
            # what the product shares with the maps held (the same tensor) costs nothing more
            held_now = self.entries[key]
            parts = value if isinstance(value, list) else [value]
            size = _nbytes([t for t in parts if not any(t is m for m in held_now)])
            need = self.next_use(key) if self.uses is not None else math.inf
            for other in self._by_distance([k for k in self.products if k != key]):
                if self.bytes + size <= self.max_bytes or (self.uses is not None and self.next_use(other) <= need):
                    break
                self._drop_products(other)
            if self.bytes + size <= self.max_bytes:
                self.products.setdefault(key, {})[name] = value
                self.product_bytes[key] = self.product_bytes.get(key, 0) + size
                self.bytes += size
                self.peak_bytes = max(self.peak_bytes, self.bytes)
        return value

    def _by_distance(self, keys: list[str]) -> list[str]:
        """Keys, needed again last first (least recently used first without a plan)."""
        if self.uses is None:
            wanted = set(keys)
            return [k for k in self.entries if k in wanted]
        return sorted(keys, key=self.next_use, reverse=True)

    def _drop_products(self, key: str) -> None:
        self.products.pop(key, None)
        self.bytes -= self.product_bytes.pop(key, 0)

    def put(self, key: str, maps: list[torch.Tensor]) -> None:
        self.seen.add(key)
        self._serve(key)
        held = compact(maps, self.compact_dtype, self.exact_levels)
        self._hold(key, held)
        if held is not maps and any(a is not b for a, b in zip(held, maps)):
            self.derived(key, "float32", lambda: maps)  # the float32 maps in hand: the widened copy

    def _serve(self, key: str) -> None:
        if self.claim is not None:
            self.served.add((key, self.claim))
            self.claim = None

    def plan(self, files_in_order: list[tuple[str, str]]) -> None:
        """The files of each pair the stage will match, in its order: the cache then keeps what
        is needed soonest. `at` tells it which pair is being matched."""
        self.uses = {}
        for k, files in enumerate(files_in_order):
            for file in dict.fromkeys(files):
                self.uses.setdefault(file, []).append(k)
        self.position = -1

    def at(self, position: int, files: tuple[str, str]) -> None:
        """The pair at `position` of the plan, with these files, is being matched."""
        self.position, self.pair_files = position, files
        self.served.clear()

    def next_use(self, key: str) -> float:
        """The plan's position of the next pair that needs key's maps: the pair being matched
        while a file of it that key belongs to has not been served yet (both, for a pair of an
        image with itself), else a later one; inf when none is known."""
        files = self.files_of.get(key, ())
        if self.pair_files is not None:
            for which, file in enumerate(self.pair_files):
                if file in files and (key, which) not in self.served:
                    return self.position
        best = math.inf
        for file in files:
            positions = (self.uses or {}).get(file, ())
            j = bisect_left(positions, self.position + 1)
            if j < len(positions):
                best = min(best, positions[j])
        return best

    def _hold(self, key: str, maps: list[torch.Tensor]) -> None:
        size = _nbytes(maps)
        if size > self.max_bytes:
            self._to_disk(key, maps)
            return
        self.entries[key] = maps
        self.bytes += size
        while self.bytes > self.max_bytes and self.products:  # products go first
            self._drop_products(self._by_distance(list(self.products))[0])
        while self.bytes > self.max_bytes:
            # needed again last out (the least recently used among equals: max keeps the first)
            old_key = next(iter(self.entries)) if self.uses is None else max(self.entries, key=self.next_use)
            old = self.entries.pop(old_key)
            self.bytes -= _nbytes(old)
            self._to_disk(old_key, old)
        self.peak_bytes = max(self.peak_bytes, self.bytes)

    def _to_disk(self, key: str, maps: list[torch.Tensor]) -> None:
        """Spill key's maps; with a plan, make room by dropping what is needed later than key
        (it is computed again then), and spill nothing that is not needed again."""
        if self.spill is None:
            return
        if self.uses is not None:
            need = self.next_use(key)
            if need == math.inf:
                return
            size = _nbytes(maps)
            while self.spill.bytes + size > self.spill.max_bytes and self.spill.sizes:
                far = max(self.spill.sizes, key=self.next_use)
                if self.next_use(far) <= need:
                    break
                self.spill.remove(far)
                self.spill.dropped += 1
        self.spill.write(key, maps)

    def belongs_to(self, key: str, which: int | None) -> None:
        """Record that key holds the maps of file `which` (0 or 1) of the pair being matched."""
        if self.pair_files is None or which is None:
            return
        self.claim = which
        self._belongs(key, self.pair_files[which])

    def _belongs(self, key: str, file: str) -> None:
        self.keys_of.setdefault(file, set()).add(key)
        self.files_of.setdefault(key, set()).add(file)

    def holds(self, key: str) -> bool:
        """Whether key's maps are in memory or on disk."""
        return key in self.entries or (self.spill is not None and key in self.spill)

    def add_ahead(self, key: str, maps: list[torch.Tensor], file: str) -> None:
        """Maps computed ahead of their pair (a batch of backbone passes) for `file` of a later
        pair of the plan: held as `put` holds them, counted as a backbone pass."""
        self.misses += 1
        self.seen.add(key)
        self._belongs(key, file)
        held = compact(maps, self.compact_dtype, self.exact_levels)
        self._hold(key, held)

    def done_with(self, file: str) -> None:
        """The file has no pair left: the maps that belong to it alone leave memory and disk."""
        for key in self.keys_of.pop(file, ()):
            files = self.files_of.get(key, set())
            files.discard(file)
            if not files:
                self.files_of.pop(key, None)
                self.forget(key)

    def forget(self, key: str) -> None:
        self._drop_products(key)
        maps = self.entries.pop(key, None)
        if maps is not None:
            self.bytes -= _nbytes(maps)
        if self.spill is not None:
            self.spill.remove(key)

    def stats(self) -> dict:
        """The counts `config.yaml: feature_reuse` records (passes per distinct image, etc.)."""
        distinct = len(self.seen)
        # extractions: backbone passes, or a two-stage matcher's features() calls
        out = {"distinct_images": distinct, "backbone_passes": self.misses, "extractions": self.misses,
               "reused": self.hits,
               "passes_per_image": round(self.misses / distinct, 4) if distinct else 0.0,
               "peak_memory_mb": round(self.peak_bytes / 2**20, 1), "products_reused": self.products_reused}
        if self.spill is not None:
            out.update(read_from_disk=self.spill.reads, written_to_disk=self.spill.writes,
                       peak_disk_mb=round(self.spill.peak_bytes / 2**20, 1), disk_full=self.spill.refused,
                       dropped_from_disk=self.spill.dropped)
        return out

    def close(self) -> None:
        """Drop every pyramid held (memory and disk)."""
        self.entries.clear()
        self.products.clear()
        self.product_bytes.clear()
        self.bytes = 0
        if self.spill is not None:
            self.spill.close()


def __getattr__(name: str):
    return moved_name(__name__, name)  # the disk tier moved to spill.py (ground/moved.py MOVED_NAMES)
