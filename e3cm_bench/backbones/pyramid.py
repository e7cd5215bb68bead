"""One image (or a batch of one size) -> its feature pyramid: `Backbone`, the network cut into
stages whose outputs are the taps, and the tensor layouts its passes use.

A Backbone turns one RGB image into feature maps f_0 .. f_{L-1}; level l has stride
2^l in ORIGINAL pixels (PROTOCOLS §1). Networks whose first usable map has stride 2
see the image upsampled 2x, so level 0 is again one cell per pixel. Only the stages up to
the deepest level used are kept, so nothing deeper is ever computed. Building one by name,
with its weights, is backbones/loading.py's `load_backbone`.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from e3cm_bench.backbones.names import MEMORY_FORMATS, PRECISIONS
from e3cm_bench.backbones.specs import MAX_LEVELS, BackboneSpec
from e3cm_bench.stats.perturb import perturb_map


class BackboneError(RuntimeError):
    """A backbone or its weights cannot be had; the message is one actionable line."""


class Backbone(nn.Module):
    """Image (1 x 3 x H x W, RGB in [0, 1]) -> list of L feature maps (C_l x H_l x W_l).

    The image is padded right/bottom to a multiple of the deepest stride 2^(L-1), so level l
    has exactly (H_pad / 2^l) x (W_pad / 2^l) cells.
    """

    def __init__(self, spec: BackboneSpec, stages: list[nn.Module], num_levels: int, weights_id: str,
                 precision: str = "fp32", memory_format: str = "auto"):
        super().__init__()
        if precision not in PRECISIONS:
            raise BackboneError(f"precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
        if memory_format not in MEMORY_FORMATS:
            raise BackboneError(f"memory_format must be one of {', '.join(MEMORY_FORMATS)}, got {memory_format!r}")
        self.precision = precision
        self.layout = memory_format
        self.name = spec.name
        self.spec = spec
        self.num_levels = num_levels
        self.upsample = spec.upsample
        self.weights_id = weights_id
        self.stages = nn.ModuleList(stages[:num_levels])
        if precision != "fp32":
            cast_weights(self.stages, REDUCED_DTYPES[precision])
        self.register_buffer("mean", torch.tensor(spec.mean).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(spec.std).view(1, 3, 1, 1), persistent=False)

    def describe(self) -> dict:
        """What a matcher's result depends on from its backbone (goes to config.yaml)."""
        return {
            "backbone": self.name,
            "backbone_taps": self.spec.taps,
            "num_levels": self.num_levels,
            "upsample": self.upsample,
            "weights": self.weights_id,
            "precision": self.precision,
            "memory_format": self.memory_format,
        }

    @property
    def memory_format(self) -> str:
        """The convolutions' layout: as set, or (auto) channels_last under reduced precision and
        where the spec says it is faster in fp32, else NCHW."""
        if self.layout != "auto":
            return self.layout
        return "channels_last" if self.precision != "fp32" or self.spec.fp32_channels_last else "nchw"

    @property
    def deepest_stride(self) -> int:
        return 2 ** (self.num_levels - 1)

    # Peak memory of matching a pair, in multiples of its two pyramids: the activations
    # alive during a pass, the pyramids themselves and what the matcher keeps beside them
    # (normalised levels, level-0 pixel rows).
    # Measured: VGG19 fp32 on a 1600 x 1200 pair peaked at 5.5 GB RSS (weights included)
    # with 1.9 GB of pyramids (docs/speed.md "Speed").
    PEAK_PER_PYRAMID = 3.0

    def pyramid_bytes(self, height: int, width: int) -> int:
        """Bytes of one image's float32 pyramid at this size (from a probe pass, once)."""
        if not hasattr(self, "_floats_per_pixel"):
            side = 2 * self.deepest_stride
            maps = self.forward(torch.zeros(1, 3, side, side, device=self.mean.device))
            self._floats_per_pixel = sum(m.numel() for m in maps) / side**2
        s = self.deepest_stride
        padded = (height + (-height) % s) * (width + (-width) % s)
        return int(4 * self._floats_per_pixel * padded)

    @torch.inference_mode()
    def forward(self, image: torch.Tensor) -> list[torch.Tensor]:
        return self.pyramid(image)[0]

    @torch.inference_mode()
    def forward_batch(self, images: torch.Tensor) -> list[list[torch.Tensor]]:
        """B x 3 x H x W -> each image's L maps, in one pass: those of `forward` image by image
        to rounding, and often bit for bit (the kernel library picks its algorithm by shape,
        batch size included; tests/matching/test_backbones.py)."""
        return self._pyramids(images, None)[0]

    @torch.inference_mode()
    def forward_with_rows(self, images: torch.Tensor) -> tuple[list[list[torch.Tensor]], list[torch.Tensor | None]]:
        """forward_batch(images), and each image's level 0 as (H W) x C pixel rows as the
        convolutions wrote them: under channels_last a pixel's channels are already one row, in
        the precision the backbone computes (bf16 rows widen to the float32 map exactly); no
        copy for one image. None in NCHW. The confidence score reads level 0 by pixels
        (matching/cascade.py): these rows spare it a transposed copy of the map."""
        maps, _, rows = self._pyramids(images, None, rows=True)
        return maps, rows

    @torch.inference_mode()
    def pyramid(self, image: torch.Tensor, stage1_tap: bool = False) -> tuple[list[torch.Tensor], torch.Tensor | None]:
        """The L maps, and with stage1_tap the map DFM's stage 1 starts from (None where the
        backbone has no such tap or fewer than 5 levels are used)."""
        tap = self.spec.stage1_tap if stage1_tap and self.num_levels == MAX_LEVELS else None
        maps, extra, _ = self._pyramids(image[:1], tap)
        return maps[0], None if extra is None else extra[0]

    def _pyramids(self, image: torch.Tensor, tap: int | None, rows: bool = False) -> tuple[
            list[list[torch.Tensor]], list[torch.Tensor] | None, list[torch.Tensor | None] | None]:
        """Each image's L maps, each one's map at module `tap` of the last stage (None: none),
        and with `rows` each one's level-0 pixel rows (forward_with_rows; else None)."""
        h, w = image.shape[-2:]
        s = self.deepest_stride
        x = (image - self.mean) / self.std
        # Zero padding after normalisation = padding with the mean colour.
        x = F.pad(x, (0, (-w) % s, 0, (-h) % s))
        if self.upsample > 1:
            x = F.interpolate(x, scale_factor=self.upsample, mode="bilinear", align_corners=False)
        # Reduced precision runs the convolutions under autocast in channels_last, their fast
        # layout on CPU and tensor cores, on weights stored in that precision (cast_weights);
        # the maps come out float32. fp32 runs in the layout the spec names (memory_format):
        # channels_last for VGG19 and Lite0, where it is faster;
        # memory_format=nchw gives VGG19 the reference releases' maps bit for bit (the parity
        # tests pass with either, tests/matching/test_parity.py).
        reduced = self.precision != "fp32"
        if self.memory_format == "channels_last":
            x = channels_last(x)
        dtype = REDUCED_DTYPES.get(self.precision)
        features, extra, level0_rows = [], None, None
        with torch.autocast(x.device.type, dtype=dtype, enabled=reduced):
            for i, stage in enumerate(self.stages):
                if tap is not None and i == len(self.stages) - 1:
                    for j, module in enumerate(stage):
                        x = module(x)
                        if j == tap:
                            extra = _maps(x)
                elif i and not (i == 1 and rows) and not _aliased(x, features[-1]):
                    held = [x]  # x's values live on in the maps (a copy): the stage may take x over
                    del x
                    x = _run_taken(stage, held)
                else:
                    x = stage(x)
                x = perturb_map(x)  # the identity outside a noise-ensemble draw (perturb.py)
                features.append(_maps(x))
                if i == 0 and rows:
                    level0_rows = pixel_rows(x)
        return [list(maps) for maps in zip(*features)], extra, level0_rows


REDUCED_DTYPES = {"bf16": torch.bfloat16, "fp16": torch.float16}


def channels_last(x: torch.Tensor) -> torch.Tensor:
    """x (N x C x H x W) in channels_last memory with the strides of a fresh channels_last
    tensor, which is how the convolutions recognise the layout.

    `x.contiguous(memory_format=torch.channels_last)` is not enough: an image made from an
    H x W x 3 array (image_to_tensor) already counts as channels_last contiguous, but its
    batch stride is 3, and torch's layout guess (suggest_memory_format) then says NCHW. The
    convolutions ran in NCHW on such inputs, and in bf16 converted every output between the
    two layouts: VGG19 at sizes that need no padding (640x480) took 1.8x as long as in
    channels_last (an unpadded image reaches the first convolution as it was made)."""
    n, c, h, w = x.shape
    if x.stride() == (c * h * w, 1, w * c, c):
        return x
    return torch.empty_like(x, memory_format=torch.channels_last).copy_(x)


def cast_weights(module: nn.Module, dtype: torch.dtype) -> None:
    """Store the weights and biases of the convolutions (and linear layers) in `dtype`, once.

    Autocast casts them to that dtype at every call, and the cast of a tensor already in it
    is the tensor itself, so the passes compute the same bits; a VGG19 pass no longer reads
    and converts its 18M float32 weights (docs/speed.md), and they take half
    the memory. Normalisation layers keep float32 parameters, as autocast leaves them."""
    for m in module.modules():
        if isinstance(m, (nn.Conv2d, nn.Linear)):
            for param in (m.weight, m.bias):
                if param is not None and param.dtype != dtype:
                    param.data = param.data.to(dtype)


def pixel_rows(x: torch.Tensor) -> list[torch.Tensor | None]:
    """Each image of a stage output (N x C x H x W) as (H W) x C rows where it is channels-last
    (views for one image; copies for a batch, so that one image's rows do not hold the
    batch's output), else None."""
    n, c = x.shape[:2]
    if x.stride(1) != 1 or not x[0].permute(1, 2, 0).is_contiguous():
        return [None] * n
    rows = [x[i].permute(1, 2, 0).reshape(-1, c) for i in range(n)]
    return rows if n == 1 else [r.clone() for r in rows]


def _aliased(x: torch.Tensor, maps: list[torch.Tensor]) -> bool:
    """Whether any of the maps shares memory with x (an NCHW float32 stage output is its own map)."""
    base = x.untyped_storage().data_ptr()
    return any(m.untyped_storage().data_ptr() == base for m in maps)


def _run_taken(stage: nn.Module, held: list[torch.Tensor]) -> torch.Tensor:
    """stage(x) for the x in `held`, which nothing else holds: a leading ReLU overwrites x in
    place (the same values as a new tensor: max(x, 0) either way) and each module's input is let
    go once the next one has it. The previous stage's output is the largest tensor of a pass
    (VGG19's level 0: 64 channels at full resolution, 380 MB at 1.5 MP in float32); kept whole
    through the stage beside its map's copy and the ReLU's output, it set the pass's peak
    (scripts/measure/e3cm_memory.py, docs/speed.md "e3cm-plus's memory per pair")."""
    x = held.pop()
    if not isinstance(stage, nn.Sequential) or type(stage[0]) is not nn.ReLU or stage._forward_hooks \
            or stage._forward_pre_hooks:
        return stage(x)  # no ReLU to run in place (Lite0): letting go earlier alone grew the kept heap
    x = torch.relu_(x)
    for module in stage[1:]:
        x = module(x)
    return x


def _maps(x: torch.Tensor) -> list[torch.Tensor]:
    """A stage output as each image's C x H x W float32 map the matching steps index (C-contiguous)."""
    return [channel_first_float(x[i]) for i in range(len(x))]


# Elements of one band of rows in channel_first_float: a few hundred KiB to 1 MiB, which
# the caches hold (256K elements measured best or within 10% of it at every level of VGG19
# and Lite0; the removed A/B script maps_copy_ab.py, in the git history). Maps of at most 4 bands are copied whole.
COPY_BAND = 1 << 18


def channel_first_float(x: torch.Tensor) -> torch.Tensor:
    """x (C x H x W) as a C-contiguous float32 map: x.float().contiguous(), the same values.

    A channels-last map (what the convolutions give under channels_last) is copied a band of
    rows at a time: torch's copy between the two layouts reads one side with a stride of C
    elements, and on a map larger than the CPU's caches that took 2.5-4x as long as copying
    bands the caches hold (VGG19 bf16 at 1200x900: 1.0 s of each image's pass went to it).
    The copy and the widening from bf16 or fp16 are exact, so the map is the same bit for bit.
    """
    if x.is_contiguous() or x.device.type != "cpu" or x.dim() != 3 or x.numel() <= 4 * COPY_BAND:
        return x.float().contiguous()  # a small map (Lite0's deepest levels) gains nothing from bands
    c, h, w = x.shape
    out = torch.empty(c, h, w, dtype=torch.float32)
    rows = max(1, COPY_BAND // (c * w))  # c * w > 0: the map has over 4 bands of elements
    for start in range(0, h, rows):
        out[:, start : start + rows].copy_(x[:, start : start + rows])
    return out
