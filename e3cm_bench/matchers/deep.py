"""What the deep matchers share: a backbone on a device, and image -> feature pyramid."""

from __future__ import annotations

import json
import math
import time

import numpy as np
import torch

from e3cm_bench.backbones.pyramid import Backbone
from e3cm_bench.matchers.base import CHANNEL_ORDERS
from e3cm_bench.matchers.base import Matcher
from e3cm_bench.matchers.feature_cache import FeatureCache
from e3cm_bench.matchers.spill import SpillStore


def image_to_tensor(image: np.ndarray, device: torch.device | str) -> torch.Tensor:
    """H x W x 3 uint8 RGB -> 1 x 3 x H x W float in [0, 1]."""
    return torch.from_numpy(np.ascontiguousarray(image)).to(device).permute(2, 0, 1)[None].float() / 255.0


class DeepMatcher(Matcher):
    """A matcher built on the feature pyramid of an ImageNet CNN (`backbones.Backbone`).

    channel_order "bgr" feeds the network the channels reversed, as the E3CM release's
    evaluation scripts do (cv2.imread without conversion); the networks were trained on RGB.
    """

    def __init__(self, backbone: Backbone, name: str, channel_order: str = "rgb"):
        if channel_order not in CHANNEL_ORDERS:
            raise ValueError(f"channel_order must be one of {', '.join(CHANNEL_ORDERS)}, got {channel_order!r}")
        self.backbone = backbone
        self.name = name
        self.channel_order = channel_order
        self.feature_cache: FeatureCache | None = None
        self._keys: dict[int, str] = {}  # the cache key of each image of the pair being matched
        self._rows: dict[int, torch.Tensor] = {}  # level-0 pixel rows of the pair's images, from their passes

    # Whether match() takes its pyramids from pyramid() (and so from the cache).
    uses_feature_cache = True
    # Whether match() reads level 0 by pixels (image_product "pixel_rows:0"): the backbone's
    # own channels-last rows are then kept with the maps (Backbone.forward_with_rows).
    wants_pixel_rows = False
    PIXEL_ROWS = "pixel_rows:0"

    def reuse_features(self, max_mb: float, spill: SpillStore | None = None) -> None:
        """Keep the pyramids of recent images (up to max_mb MiB, then in `spill` on disk) for
        pairs that share an image; maps of a bf16 or fp16 backbone are held in that precision."""
        narrow = {"bf16": torch.bfloat16, "fp16": torch.float16}.get(getattr(self.backbone, "precision", "fp32"))
        self.feature_cache = FeatureCache(max_mb, spill, narrow) if max_mb > 0 else None

    def feature_identity(self) -> str:
        """Everything an image's pyramid depends on besides the image itself."""
        return json.dumps({**self.backbone.describe(), "channel_order": self.channel_order,
                           "device": str(self.device)}, sort_keys=True)

    def share_features_of(self, other: DeepMatcher, max_mb: float, spill: SpillStore | None = None) -> None:
        """Take other's backbone (when built apart) and feature cache (made if it has none), so
        that the two matchers pass each image through the network once between them."""
        if other.feature_identity() != self.feature_identity():
            raise ValueError("matchers with different backbone settings cannot share feature maps")
        if other.feature_cache is None:
            other.reuse_features(max_mb, spill)
        self.backbone, self.feature_cache = other.backbone, other.feature_cache

    @property
    def device(self) -> torch.device:
        return self.backbone.mean.device

    def network_input(self, image: np.ndarray) -> torch.Tensor:
        if self.channel_order == "bgr":
            image = image[..., ::-1]
        return image_to_tensor(image, self.device)

    def pyramid(self, image: np.ndarray, which: int | None = None) -> list[torch.Tensor]:
        """The image's pyramid: level l is C_l x H_l x W_l at stride 2^l. which: 0 or 1, the
        image's place in the pair the match stage is matching (the cache learns which file
        the maps belong to, and drops them once that file has no pair left)."""
        if which is not None:
            self._rows.pop(which, None)  # rows of an earlier image in that place
        if self.feature_cache is None:
            return self._pass(image, which)
        if which is None and self.feature_cache.pair_files is not None:
            # an image made inside the pair (B warped by a homography, e3cm-plus's prewarp and
            # realign) while the match stage runs: no file of the plan is it, so nothing would ever
            # release it, and its maps sat in memory until the budget (half the memory) was full:
            # e3cm-plus peaked near 8 GB on full-size HPatches pairs. Its content is new each time,
            # so the cache would never serve it again: it is passed and not kept.
            return self._pass(image, which)
        key = self.image_key(image)
        if which is not None:
            self._keys[which] = key
        self.feature_cache.belongs_to(key, which)
        maps = self.feature_cache.get(key, self.device)
        if maps is None:
            maps = self._pass(image, which)
            self.feature_cache.put(key, maps)
            if which in self._rows:
                self.feature_cache.derived(key, self.PIXEL_ROWS, lambda: self._rows[which])
        return maps

    def _pass(self, image: np.ndarray, which: int | None) -> list[torch.Tensor]:
        """The image's pyramid from the backbone; its level-0 pixel rows are kept for the
        pair's image `which` where match() reads them and the backbone has them."""
        if not self.wants_pixel_rows:
            return self.backbone(self.network_input(image))
        (maps,), (rows,) = self.backbone.forward_with_rows(self.network_input(image))
        if rows is not None and which is not None:
            self._rows[which] = rows
        return maps

    def image_key(self, image: np.ndarray) -> str:
        """The feature cache's key of an image as match() is given it."""
        return FeatureCache.key(image, self.channel_order)

    def prefetch(self, images: list[tuple[str, str, np.ndarray]], batch: int) -> list[int]:
        """Pass the images (image_key, file, image as match() will be given it) that the
        feature cache lacks through the backbone up to `batch` at a time, those of one size
        together, into the cache for their files. A batch is halved while the device's free
        memory is short of it (check_memory). Returns the size of each batch run."""
        cache = self.feature_cache
        if cache is None:
            return []
        todo: dict[str, tuple[str, str, np.ndarray]] = {}
        for item in images:
            if item[0] not in todo and not cache.holds(item[0]):
                todo[item[0]] = item
        by_size: dict[tuple, list[tuple[str, str, np.ndarray]]] = {}
        for item in todo.values():
            by_size.setdefault(item[2].shape, []).append(item)
        sizes = []
        for items in by_size.values():
            while items:
                n = min(batch, len(items))
                while n > 1 and not self._fits(items[:n]):
                    n //= 2
                chunk, items = items[:n], items[n:]
                stacked = torch.cat([self.network_input(image) for _, _, image in chunk])
                if self.wants_pixel_rows:
                    maps_of, rows_of = self.backbone.forward_with_rows(stacked)
                else:
                    maps_of, rows_of = self.backbone.forward_batch(stacked), [None] * n
                for (key, file, _), maps, rows in zip(chunk, maps_of, rows_of):
                    cache.add_ahead(key, maps, file)
                    if rows is not None:
                        cache.derived(key, self.PIXEL_ROWS, lambda rows=rows: rows)
                sizes.append(n)
        return sizes

    def _fits(self, images: list[tuple[str, str, np.ndarray]]) -> bool:
        try:
            self.check_memory(*[image for _, _, image in images])
        except MemoryError:
            return False
        return True

    def image_product(self, which: int, name: str, compute):
        """compute(): a product of the maps of image `which` (0 or 1) of the pair whose pyramids
        were just fetched, kept with them in the feature cache (FeatureCache.derived) so that
        the image's later pairs reuse it; computed each time without a cache. The level-0
        pixel rows of an image passed through the backbone for this pair are those of the pass."""
        if name == self.PIXEL_ROWS and which in self._rows:
            return self._rows[which]
        if self.feature_cache is None or which not in self._keys:
            return compute()
        return self.feature_cache.derived(self._keys[which], name, compute)

    def check_memory(self, *images: np.ndarray) -> None:
        """MemoryError, before anything is allocated, when matching these images would need
        more memory than the device has free (an out-of-memory kill loses the message)."""
        free = available_memory(self.device)
        if free is None:
            return
        need = self.backbone.PEAK_PER_PYRAMID * sum(self.backbone.pyramid_bytes(*im.shape[:2]) for im in images)
        if need > free:
            longest = max(max(im.shape[:2]) for im in images)
            fits = int(longest * math.sqrt(free / need)) // 16 * 16
            raise MemoryError(f"about {need / 2**30:.1f} GiB needed at {longest} px, {free / 2**30:.1f} GiB free; "
                              f"--max-side {fits} would fit")

    def pyramids(self, image0: np.ndarray, image1: np.ndarray) -> tuple[list[torch.Tensor], list[torch.Tensor], float]:
        """Both images' pyramids and the seconds the backbone took."""
        self.check_memory(image0, image1)
        t = time.perf_counter()
        self._keys.clear()
        feats0, feats1 = self.pyramid(image0, 0), self.pyramid(image1, 1)
        return feats0, feats1, time.perf_counter() - t

    def settings_dict(self) -> dict:  # pragma: no cover - each subclass says what it depends on
        raise NotImplementedError

    def config(self) -> dict:
        return {"matcher": self.name, **self.backbone.describe(), "channel_order": self.channel_order,
                **self.settings_dict()}


# Backbone passes batched ahead of their pairs (--backbone-batch; match_jobs): on a GPU, where
# one image does not fill the device; on a CPU a pass already keeps every core busy.
GPU_BATCH = 8


def auto_backbone_batch(device: torch.device | str) -> int:
    return GPU_BATCH if torch.device(device).type == "cuda" else 1


def available_memory(device: torch.device) -> int | None:
    """Bytes free for new tensors: the GPU's free memory, or the host's MemAvailable (Linux);
    None where it cannot be read."""
    if device.type == "cuda":
        return torch.cuda.mem_get_info(device)[0]
    from e3cm_bench.ground.devices import available_host_memory

    return available_host_memory()


def level0_cosine(map0: torch.Tensor, map1: torch.Tensor, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
    """Cosine of the level-0 features at each match of integer level-0 pixels (the releases
    give no score; this one orders their matches for display and PROSAC-style use)."""
    if len(x0) == 0:
        return np.zeros(0, np.float32)
    p0 = torch.from_numpy(np.rint(x0).astype(np.int64)).to(map0.device)
    p1 = torch.from_numpy(np.rint(x1).astype(np.int64)).to(map1.device)
    a = torch.nn.functional.normalize(map0[:, p0[:, 1], p0[:, 0]], dim=0)
    b = torch.nn.functional.normalize(map1[:, p1[:, 1], p1[:, 0]], dim=0)
    return (a * b).sum(0).float().cpu().numpy()
