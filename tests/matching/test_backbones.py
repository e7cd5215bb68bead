"""Backbones as feature pyramids (e3cm_bench.backbones.loading, pyramid): shapes, truncation, weights handling."""

from __future__ import annotations

import functools
import http.server
import math
import threading
from pathlib import Path

import numpy as np
import pytest
import torch

from e3cm_bench.backbones import loading as backbones, pyramid
from e3cm_bench.backbones.loading import BACKBONES, SPECS, BackboneError, load_backbone

H, W = 97, 131  # an odd size: padding to the deepest stride is exercised


def expected_shape(level: int, num_levels: int = 5) -> tuple[int, int]:
    s = 2 ** (num_levels - 1)
    return math.ceil(H / s) * s // 2**level, math.ceil(W / s) * s // 2**level


@pytest.fixture(scope="module")
def image() -> torch.Tensor:
    return torch.rand(1, 3, H, W, generator=torch.Generator().manual_seed(0))


@pytest.mark.parametrize("name", BACKBONES)
def test_every_backbone_gives_five_levels(name, image):
    torch.manual_seed(0)
    bb = load_backbone(name, pretrained=False)
    assert bb.weights_id == "random" and bb.num_levels == 5 and len(bb.stages) == 5
    feats = bb(image)
    assert len(feats) == 5
    # Level l: stride 2^l in original pixels, image padded to a multiple of 16:
    # 97 x 131 -> 112 x 144 -> (112, 144), (56, 72), (28, 36), (14, 18), (7, 9).
    for level, f in enumerate(feats):
        assert f.dim() == 3 and f.shape[0] > 0, (name, level)
        assert tuple(f.shape[1:]) == expected_shape(level), (name, level, tuple(f.shape))
        assert torch.isfinite(f).all()
    if name == "vgg19":
        # PROTOCOLS §1: conv1_2, conv2_2, conv3_2, conv4_2, conv5_3.
        assert [f.shape[0] for f in feats] == [64, 128, 256, 512, 512]
        # Taps are taken before their ReLU, and the next stage's ReLU did not overwrite them.
        assert all(bool((f < 0).any()) for f in feats)


@pytest.mark.parametrize("name,precision", [("vgg19", "fp32"), ("efficientnet_lite0", "fp32"), ("efficientnet_lite0", "bf16")])
def test_a_batch_of_images_gives_each_the_maps_of_its_own_pass(name, precision):
    """forward_batch (the match stage's batches ahead, --backbone-batch): each image's maps
    are those of a pass of that image alone, to rounding. Not always bit for bit: the kernel
    library picks its algorithm by shape (on this project's CPU, identical at this size and at
    240x320 and 640x480, 1e-6 apart for VGG19 at 64x48)."""
    torch.manual_seed(0)
    bb = load_backbone(name, pretrained=False, precision=precision)
    images = torch.rand(3, 3, H, W, generator=torch.Generator().manual_seed(2))
    batched = bb.forward_batch(images)
    assert len(batched) == 3
    for i, maps in enumerate(batched):
        alone = bb(images[i:i + 1])
        assert [tuple(m.shape) for m in maps] == [tuple(m.shape) for m in alone]
        assert all(m.dtype == torch.float32 and m.is_contiguous() for m in maps)
        for a, b in zip(maps, alone):
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5 * float(b.abs().max()))
    assert not torch.equal(batched[0][4], batched[1][4])  # each image its own maps


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16, torch.float32])
def test_channel_first_float_is_the_plain_copy_bit_for_bit(dtype, monkeypatch):
    """The banded copy of a channels-last map gives x.float().contiguous() exactly: every
    band, the last one short (37 rows in bands of 3), and the widening from 2 bytes."""
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(1, 24, 37, 53, generator=gen).to(dtype).contiguous(memory_format=torch.channels_last)[0]
    assert not x.is_contiguous()
    monkeypatch.setattr(pyramid, "COPY_BAND", 3 * 24 * 53)  # 12 bands of 3 rows and 1 of 1
    got = pyramid.channel_first_float(x)
    assert got.dtype == torch.float32 and got.is_contiguous()
    assert torch.equal(got, x.float().contiguous())
    # A map already C-contiguous is widened as before (no copy where it is float32 already).
    flat = torch.randn(8, 5, 7, generator=gen)
    assert pyramid.channel_first_float(flat) is flat


@pytest.mark.parametrize("name,precision", [("vgg19", "bf16"), ("efficientnet_lite0", "bf16"),
                                            ("efficientnet_lite0", "fp16")])
def test_weights_cast_once_give_the_maps_of_casting_them_at_each_pass(name, precision, image, monkeypatch):
    """A reduced-precision backbone stores its convolutions' weights in that precision when it
    is built (normalisation layers stay float32); its maps are those of leaving them float32
    for autocast to cast at every pass, bit for bit."""
    dtype = pyramid.REDUCED_DTYPES[precision]
    torch.manual_seed(0)
    once = load_backbone(name, pretrained=False, precision=precision)
    monkeypatch.setattr(pyramid, "cast_weights", lambda module, to: None)
    torch.manual_seed(0)
    each = load_backbone(name, pretrained=False, precision=precision)
    convs = [m for m in once.modules() if isinstance(m, torch.nn.Conv2d)]
    assert convs and all(m.weight.dtype == dtype for m in convs)
    assert all(p.dtype == torch.float32 for m in once.modules() if isinstance(m, torch.nn.BatchNorm2d)
               for p in m.parameters())
    assert all(p.dtype == torch.float32 for p in each.parameters())
    assert all(torch.equal(a, b) for a, b in zip(once(image), each(image)))


@pytest.mark.parametrize("name,precision", [("vgg19", "bf16"), ("efficientnet_lite0", "fp32")])
def test_channels_last_passes_give_c_contiguous_maps_equal_to_the_plain_copy(name, precision, image, monkeypatch):
    """The maps of a channels_last pass (VGG19 in bf16, Lite0 in fp32) are those of the plain
    copy bit for bit, C-contiguous float32, as the matching steps index them."""
    torch.manual_seed(0)
    bb = load_backbone(name, pretrained=False, precision=precision)
    assert bb.memory_format == "channels_last"
    banded = bb(image)
    monkeypatch.setattr(pyramid, "_maps", lambda x: [x[i].float().contiguous() for i in range(len(x))])
    plain = bb(image)
    for a, b in zip(banded, plain):
        assert a.dtype == torch.float32 and a.is_contiguous()
        assert torch.equal(a, b)


def test_channels_last_strides_are_those_of_a_fresh_channels_last_tensor():
    """pyramid.channels_last: an image made from an H x W x 3 array (batch stride 3), which
    torch's layout guess takes for NCHW, is copied to the strides of a fresh channels_last
    tensor; a tensor that has them already is handed back as it is."""
    from e3cm_bench.matchers.deep import image_to_tensor

    array = (np.arange(16 * 32 * 3) % 251).astype(np.uint8).reshape(16, 32, 3)
    odd = image_to_tensor(array, "cpu")
    assert odd.is_contiguous(memory_format=torch.channels_last) and odd.stride(0) == 3
    assert odd.contiguous(memory_format=torch.channels_last).stride(0) == 3  # why that is not enough
    fixed = pyramid.channels_last(odd)
    assert fixed.stride() == (3 * 16 * 32, 1, 32 * 3, 3) and torch.equal(fixed, odd)
    assert pyramid.channels_last(fixed) is fixed


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_an_unpadded_image_made_from_an_array_runs_in_channels_last(precision):
    """VGG19 on an image that needs no padding (64 x 48), made as the matchers make it
    (image_to_tensor): its convolutions run in channels_last (their outputs are
    channels-last), as the layout setting says."""
    from e3cm_bench.matchers.deep import image_to_tensor

    torch.manual_seed(0)
    bb = load_backbone("vgg19", pretrained=False, precision=precision, num_levels=2)
    assert bb.memory_format == "channels_last"
    outputs = []
    hook = bb.stages[0][0].register_forward_hook(lambda module, args, out: outputs.append(out))
    try:
        bb(image_to_tensor(np.full((48, 64, 3), 128, np.uint8), "cpu"))
    finally:
        hook.remove()
    assert outputs[0].is_contiguous(memory_format=torch.channels_last) and not outputs[0].is_contiguous()


def test_memory_format_setting(image):
    """VGG19's fp32 passes run channels_last by default (faster once its maps are copied out in
    bands); memory_format=nchw runs them as the releases do. The maps agree to rounding."""
    torch.manual_seed(0)
    default = load_backbone("vgg19", pretrained=False)
    nchw = load_backbone("vgg19", pretrained=False, memory_format="nchw")
    nchw.load_state_dict(default.state_dict())
    assert default.memory_format == "channels_last" and nchw.memory_format == "nchw"
    assert default.describe()["memory_format"] == "channels_last"
    for a, b in zip(default(image), nchw(image)):
        assert a.is_contiguous() and b.is_contiguous()
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5 * float(b.abs().max()))
    assert load_backbone("vgg19", pretrained=False, precision="bf16", memory_format="nchw").memory_format == "nchw"
    with pytest.raises(BackboneError, match="memory_format must be one of auto, nchw, channels_last"):
        load_backbone("vgg19", pretrained=False, memory_format="nhwc")


def test_num_levels_truncates_the_network(image):
    full = load_backbone("efficientnet_lite0")
    three = load_backbone("efficientnet_lite0", num_levels=3)
    assert len(three.stages) == 3 and three.num_levels == 3 and three.deepest_stride == 4
    n_full = sum(p.numel() for p in full.parameters())
    n_three = sum(p.numel() for p in three.parameters())
    assert n_three < n_full / 5  # the deep blocks hold most of the weights; they are gone
    feats = three(image)
    assert len(feats) == 3
    # Padding is now to a multiple of 4 only: 97 x 131 -> 100 x 132.
    assert [tuple(f.shape[1:]) for f in feats] == [(100, 132), (50, 66), (25, 33)]
    # On an image that needs no padding either way, the shallow levels are identical.
    img = torch.rand(1, 3, 64, 96, generator=torch.Generator().manual_seed(1))
    for a, b in zip(three(img), full(img)[:3]):
        torch.testing.assert_close(a, b)
    with pytest.raises(BackboneError, match="num_levels"):
        load_backbone("efficientnet_lite0", pretrained=False, num_levels=6)
    with pytest.raises(BackboneError, match="num_levels"):
        load_backbone("efficientnet_lite0", pretrained=False, num_levels=0)


def test_efficientnet_lite0_packaged_weights():
    bb = load_backbone("efficientnet_lite0")
    assert "sha256:" in bb.weights_id and bb.weights_id != "random"
    assert Path(bb.weights_id.split(" sha256:")[0]).is_file()
    # Loaded, not random: the same weights twice give identical parameters.
    again = load_backbone("efficientnet_lite0")
    for p, q in zip(bb.parameters(), again.parameters()):
        assert torch.equal(p, q)
    assert bb.weights_id == again.weights_id


@pytest.mark.parametrize("name", ["efficientnet_lite0", "mobilenet_v3_large"])
def test_weights_file_is_loaded(name, tmp_path):
    torch.manual_seed(1)
    model = SPECS[name].build()
    state = model.state_dict()
    path = tmp_path / f"{name}-custom.pth"
    torch.save(state, path)
    bb = load_backbone(name, weights=path)
    assert str(path) in bb.weights_id and "sha256:" in bb.weights_id
    loaded = {k: v for k, v in bb.state_dict().items()}
    # Every parameter of the kept stages comes from the file (compare by value).
    saved_values = [v for v in state.values() if v.dtype.is_floating_point]
    for value in loaded.values():
        if value.dtype.is_floating_point and value.numel() > 16:
            assert any(value.shape == s.shape and torch.equal(value, s) for s in saved_values)
    # A file saved as {"state_dict": ...} is accepted too.
    wrapped = tmp_path / "wrapped.pth"
    torch.save({"state_dict": state}, wrapped)
    assert str(wrapped) in load_backbone(name, weights=wrapped).weights_id


def assert_one_line(err: pytest.ExceptionInfo, *fragments: str) -> str:
    message = str(err.value)
    assert "\n" not in message
    for fragment in fragments:
        assert fragment in message, (fragment, message)
    return message


def test_weights_file_errors(tmp_path):
    missing = tmp_path / "nope.pth"
    with pytest.raises(BackboneError) as err:
        load_backbone("efficientnet_lite0", weights=missing)
    assert_one_line(err, str(missing), "not found")

    wrong = tmp_path / "mobilenet.pth"
    torch.save(SPECS["mobilenet_v3_large"].build().state_dict(), wrong)
    with pytest.raises(BackboneError) as err:
        load_backbone("efficientnet_lite0", weights=wrong)
    assert_one_line(err, str(wrong), "efficientnet_lite0")

    garbage = tmp_path / "garbage.pth"
    garbage.write_text("not a checkpoint\nat all\n")
    with pytest.raises(BackboneError) as err:
        load_backbone("efficientnet_lite0", weights=garbage)
    assert_one_line(err, str(garbage))

    a_list = tmp_path / "list.pth"
    torch.save([1, 2, 3], a_list)
    with pytest.raises(BackboneError) as err:
        load_backbone("efficientnet_lite0", weights=a_list)
    assert_one_line(err, str(a_list), "state dict")


def test_unknown_backbone_lists_choices():
    with pytest.raises(BackboneError) as err:
        load_backbone("alexnet")
    message = assert_one_line(err, "alexnet")
    for name in BACKBONES:
        assert name in message


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args) -> None:  # keep the test output clean
        pass


def test_torchvision_weights_download_then_cache(tmp_path, monkeypatch):
    # The torchvision path (torch hub cache, then download) against a local server. The
    # weights are a random MobileNetV3-Large state dict (21 MB; the code path is the same for
    # every torchvision backbone, and VGG19's 548 MB would only slow the test down).
    name = "mobilenet_v3_large"
    filename = f"{name}-random.pth"  # no hex after '-': torch hub does no hash check
    served = tmp_path / "served"
    served.mkdir()
    torch.manual_seed(2)
    state = SPECS[name].build().state_dict()
    torch.save(state, served / filename)
    for var in ("http_proxy", "HTTP_PROXY", "https_proxy", "HTTPS_PROXY", "all_proxy", "ALL_PROXY"):
        monkeypatch.delenv(var, raising=False)
    torch_home = tmp_path / "torch_home"
    monkeypatch.setenv("TORCH_HOME", str(torch_home))

    server = http.server.ThreadingHTTPServer(
        ("127.0.0.1", 0), functools.partial(_QuietHandler, directory=str(served))
    )
    port = server.server_address[1]
    url = f"http://127.0.0.1:{port}/{filename}"
    monkeypatch.setattr(backbones, "imagenet_weights_url", lambda spec: url)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        cached = torch_home / "hub" / "checkpoints" / filename
        assert backbones.hub_checkpoint_dir() == torch_home / "hub" / "checkpoints"
        assert not cached.exists()
        bb = load_backbone(name)
        assert cached.is_file()
        assert str(cached) in bb.weights_id and "sha256:" in bb.weights_id
        first_conv = bb.stages[0][0][0].weight
        torch.testing.assert_close(first_conv, state["features.0.0.weight"])
    finally:
        server.shutdown()
        server.server_close()
        thread.join(timeout=5)

    # Server gone: the cached file is used.
    bb2 = load_backbone(name)
    assert bb2.weights_id == bb.weights_id
    torch.testing.assert_close(bb2.stages[0][0][0].weight, state["features.0.0.weight"])

    # Server gone and an empty cache: one actionable line.
    empty_home = tmp_path / "empty_home"
    monkeypatch.setenv("TORCH_HOME", str(empty_home))
    with pytest.raises(BackboneError) as err:
        load_backbone(name)
    expected_path = empty_home / "hub" / "checkpoints" / filename
    assert_one_line(err, str(expected_path), "--weights", name, url)
    assert not expected_path.exists()


@pytest.mark.parametrize("name,precision", [("vgg19", "bf16"), ("vgg19", "fp32"), ("efficientnet_lite0", "fp16")])
def test_level0_rows_are_the_pass_own_channels_last_pixels(name, precision):
    """forward_with_rows: each image's level 0 as (H W) x C rows, in the precision the
    convolutions computed, widening to its float32 map exactly; each holding its own image's
    rows only (a batch's are copied out of its output); none where the pass ran in NCHW."""
    torch.manual_seed(0)
    bb = load_backbone(name, pretrained=False, precision=precision)
    assert bb.memory_format == "channels_last"
    images = torch.rand(2, 3, H, W, generator=torch.Generator().manual_seed(4))
    for batch in (images[:1], images):
        maps_of, rows_of = bb.forward_with_rows(batch)
        assert len(maps_of) == len(rows_of) == len(batch)
        for maps, rows in zip(maps_of, rows_of):
            c, h, w = maps[0].shape
            assert rows.shape == (h * w, c) and rows.is_contiguous()
            assert rows.dtype == (torch.float32 if precision == "fp32" else pyramid.REDUCED_DTYPES[precision])
            assert torch.equal(rows.float(), maps[0].permute(1, 2, 0).reshape(-1, c))
            # Its storage holds this image's rows alone, not the batch's output.
            assert rows.untyped_storage().nbytes() == rows.numel() * rows.element_size()
        assert all(torch.equal(a, b) for a, b in zip(maps_of[0], bb(batch[:1])))
    nchw = load_backbone(name, pretrained=False, precision="fp32", memory_format="nchw")
    maps_of, rows_of = nchw.forward_with_rows(images[:1])
    assert rows_of == [None] and len(maps_of[0]) == 5


@pytest.mark.parametrize("name,precision,memory_format", [("vgg19", "fp32", "auto"), ("vgg19", "fp32", "nchw"),
                                                         ("vgg19", "bf16", "auto"), ("efficientnet_lite0", "fp32", "auto")])
def test_a_stage_taking_over_its_input_gives_the_same_maps_bit_for_bit(name, precision, memory_format, image,
                                                                       monkeypatch):
    """_run_taken (the leading ReLU in place, each input let go) against the stage called whole."""
    torch.manual_seed(0)
    bb = load_backbone(name, pretrained=False, precision=precision, memory_format=memory_format)
    taken = bb(image)
    monkeypatch.setattr(pyramid, "_run_taken", lambda stage, held: stage(held.pop()))
    whole = bb(image)
    assert all(torch.equal(a, b) for a, b in zip(taken, whole, strict=True))


def test_level0_output_is_let_go_before_the_next_stage_ends(image):
    """VGG19's level-0 output (the pass's largest tensor) is freed inside stage 1 once its map is
    copied (channels_last), not held through the stage: what lowers the pass's peak."""
    import weakref

    torch.manual_seed(0)
    bb = load_backbone("vgg19", pretrained=False)
    assert bb.memory_format == "channels_last"
    outputs, alive = [], []
    bb.stages[0].register_forward_hook(lambda module, args, out: outputs.append(weakref.ref(out)))
    bb.stages[1][-1].register_forward_hook(lambda module, args, out: alive.append(outputs[-1]() is not None))
    maps = bb(image)
    assert alive == [False] and len(maps) == 5
    rows_maps, rows = bb.forward_with_rows(image)  # level-0 rows are views of that output: it is kept
    assert alive == [False, True] and rows[0] is not None
