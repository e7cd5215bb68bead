"""The speed machinery changes no result: decoding ahead, feature sharing across methods, batched
backbone passes, the banded copy of the maps, weights cast once, the ordered norm, the widened
gather, and glibc keeping freed memory."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import yaml

from e3cm_bench.backbones import loading as backbones, pyramid
from e3cm_bench.benchmarks import get_benchmark
from e3cm_bench.datasets.base import Pair
from e3cm_bench.ground.images import ImageError
from e3cm_bench.matching import norms
from e3cm_bench.matching.cascade import UnitPixels
from e3cm_bench.method.spec import MethodSpec
from e3cm_bench.pipeline.match_options import MatchOptions
from e3cm_bench.pipeline.stage import decoded_ahead
from e3cm_bench.pipeline.runner import run_benchmark, run_methods
from helpers import assert_same_arrays

GLIBC = platform.libc_ver()[0] == "glibc"  # keep_freed_memory tunes glibc's malloc only


def test_decoded_ahead_yields_each_pairs_images_and_its_own_error(tmp_path: Path):
    rng = np.random.default_rng(0)
    paths = []
    for i in range(3):
        path = tmp_path / f"{i}.png"
        cv2.imwrite(str(path), rng.integers(0, 255, (8 + i, 10, 3), dtype=np.uint8))
        paths.append(path)
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(b"\xff\xd8\xff not a whole jpeg")
    pairs = [Pair("a", paths[0], paths[1]), Pair("b", paths[1], bad), Pair("c", paths[2], paths[0])]
    seen, ahead = [], []
    with ThreadPoolExecutor(max_workers=1) as executor:
        for pair, images, coming in decoded_ahead(pairs, executor, ahead=2):
            ahead.append([p.name for p, _ in coming])
            if pair.name == "b":
                with pytest.raises(ImageError, match="bad.jpg"):
                    images.result()
                continue
            image0, image1 = images.result()
            seen.append((pair.name, image0.shape[0], image1.shape[0]))
    assert seen == [("a", 8, 9), ("c", 10, 8)]
    assert ahead == [["b", "c"], ["c"], []]  # the coming pairs, decoding while the current one is matched


def test_feature_reuse_gives_byte_identical_matches(shared_data, tmp_path):
    """Pairs sharing image 1 of a sequence: with the feature cache each image passes through the
    backbone once, and the cached matches are byte-identical to those of a run without it."""
    method = MethodSpec.create("direct", "efficientnet_lite0", max_side=320)
    hp = get_benchmark("hpatches")
    root = shared_data / "hpatches-sequences-release"
    run_benchmark(hp, tmp_path / "reuse", method, root=root, dataset_options={"sequences": ["v_boat"]}, limit=3)
    config = yaml.safe_load((tmp_path / "reuse" / "config.yaml").read_text())
    assert config["feature_reuse"]["backbone_passes"] == 4 and config["feature_reuse"]["reused"] == 2
    if GLIBC:  # a run keeps freed memory for its next pass, and says so
        assert config["environment"]["allocator"] == "glibc, freed memory kept (M_MMAP_MAX=0, no trim, one arena)"

    run_benchmark(hp, tmp_path / "plain", method, root=root, dataset_options={"sequences": ["v_boat"]}, limit=3,
                  options=MatchOptions(feature_cache_mb=0))
    assert "feature_reuse" not in yaml.safe_load((tmp_path / "plain" / "config.yaml").read_text())

    assert_same_arrays(tmp_path / "reuse", tmp_path / "plain")


@pytest.mark.slow  # 38 s alone on a loaded 2-core machine (docs/development.md, Testing)
def test_methods_matched_together_share_maps_and_give_the_same_matches(shared_data, tmp_path, monkeypatch):
    """reproduce's joint stage: e3cm, direct and e3cm-release (one backbone setting) on three
    pairs with four distinct images load the weights once and pass each image through the
    network once between them (4 passes, not 3 x 6), and each method's matches equal those
    of its own run. The normalised maps e3cm and direct make of an image are made once and
    shared too (FeatureCache.derived), and change nothing either."""
    import e3cm_bench.backbones.loading as backbones

    loads = []
    real_load = backbones.load_backbone

    def counted_load(*args, **kwargs):
        loads.append(args[0] if args else kwargs.get("name"))
        return real_load(*args, **kwargs)

    monkeypatch.setattr(backbones, "load_backbone", counted_load)
    hp = get_benchmark("hpatches")
    dataset = hp.load_dataset(shared_data / "hpatches-sequences-release", sequences=["v_boat"])
    methods = [MethodSpec.create(m, "efficientnet_lite0", max_side=320) for m in ("e3cm", "direct", "e3cm-release")]
    sift = MethodSpec.create("sift", max_side=320)
    run_methods(hp, [(tmp_path / "joint" / m.folder, m) for m in [*methods, sift]], dataset, limit=3)
    assert loads == ["efficientnet_lite0"]
    for method in methods:
        config = yaml.safe_load((tmp_path / "joint" / method.folder / "config.yaml").read_text())
        assert config["feature_reuse"]["shared_by"] == [m.label for m in methods]
        assert config["feature_reuse"]["backbone_passes"] == 4 and config["feature_reuse"]["reused"] == 14
        assert config["feature_reuse"]["products_reused"] > 0
    for method in [*methods, sift]:
        run_benchmark(hp, tmp_path / "alone" / method.folder, method, dataset=dataset, limit=3, options=MatchOptions(feature_cache_mb=0))
        assert_same_arrays(tmp_path / "joint" / method.folder, tmp_path / "alone" / method.folder)


def test_a_pair_too_big_for_free_memory_is_refused_before_allocating(tmp_path, monkeypatch):
    """With 1 GiB free (patched), a 1600 x 1200 pair at full resolution is refused up front, in
    one line that names the --max-side that fits; with that side the same run succeeds."""
    import e3cm_bench.matchers.deep as deep
    from typer.testing import CliRunner

    from e3cm_bench.cli import app
    from helpers import one_line_error

    root = tmp_path / "hp"
    (root / "v_big").mkdir(parents=True)
    noise = np.random.default_rng(0).integers(0, 256, (60, 80, 3), dtype=np.uint8)
    image = cv2.resize(noise, (1600, 1200), interpolation=cv2.INTER_LINEAR)
    for k in range(1, 7):
        cv2.imwrite(str(root / "v_big" / f"{k}.ppm"), image)
        if k > 1:
            np.savetxt(root / "v_big" / f"H_1_{k}", np.eye(3))
    monkeypatch.setattr(deep, "available_memory", lambda device: 1 << 30)
    args = ["hpatches", "--root", str(root), "--backbone", "efficientnet_lite0", "--limit", "1"]
    line = one_line_error(CliRunner().invoke(app, [*args, "--out", str(tmp_path / "full"), "--max-side", "0"]))
    assert "do not fit in memory" in line and "GiB free" in line
    fits = int(line.split("--max-side ")[1].split()[0])
    assert 0 < fits < 1600
    done = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "fits"), "--max-side", str(fits)])
    assert done.exit_code == 0, done.output


def test_a_6000_by_4000_pair_fits_or_names_max_side():
    """The real machine: VGG19 (random weights) on a 6000 x 4000 pair either fits in the free
    memory or stops before allocating, naming --max-side."""
    from e3cm_bench.matchers.deep import available_memory
    from e3cm_bench.pipeline.runner import match_pair

    matcher = MethodSpec.create("e3cm", "vgg19").build("cpu", pretrained=False)
    need = 6 * matcher.backbone.pyramid_bytes(4000, 6000)
    free = available_memory(matcher.device)
    if free is None or need <= free:
        pytest.skip(f"this machine has {free} bytes free: a 6000 x 4000 pair fits (or memory is unknown)")
    image = np.zeros((4000, 6000, 3), np.uint8)
    with pytest.raises(MemoryError, match=r"--max-side \d+ would fit"):
        match_pair(matcher, image, image)


def test_a_batch_of_images_gives_each_images_maps_within_rounding():
    """backbone.forward_batch (what --backbone-batch uses) on three images in batches of two
    gives the maps of passing them one by one, within float32 rounding."""
    torch.manual_seed(0)
    backbone = backbones.load_backbone("efficientnet_lite0", pretrained=False)
    images = torch.rand(3, 3, 48, 64, generator=torch.Generator().manual_seed(0))
    alone = [backbone(images[i:i + 1]) for i in range(len(images))]
    together = [maps for start in (0, 2) for maps in backbone.forward_batch(images[start:start + 2])]
    assert len(together) == 3 and all(len(x) == len(y) for x, y in zip(alone, together))
    for x, y in zip(alone, together):
        for a, b in zip(x, y):
            assert a.shape == b.shape and (a - b).abs().max().item() < 1e-4


def test_the_banded_copy_of_each_level_equals_torchs_copy(monkeypatch):
    """pyramid.channel_first_float on the real channels-last output of every stage of a bf16
    backbone whose level 0 (16 x 240 x 320, over 1M elements) takes the banded copy: the same
    C-contiguous float32 maps as torch's copy, bit for bit."""
    torch.manual_seed(0)
    backbone = backbones.load_backbone("efficientnet_lite0", pretrained=False, precision="bf16")
    assert backbone.memory_format == "channels_last"
    outputs, maps = [], pyramid._maps
    monkeypatch.setattr(pyramid, "_maps", lambda x: outputs.append(x[0]) or maps(x))
    backbone.forward(torch.rand(1, 3, 240, 320, generator=torch.Generator().manual_seed(0)))
    assert len(outputs) == 5 and tuple(outputs[0].shape) == (16, 240, 320) and outputs[0].dtype == torch.bfloat16
    for x in outputs:
        copy = pyramid.channel_first_float(x)
        assert copy.is_contiguous() and torch.equal(copy, x.float().contiguous())


def test_weights_cast_once_give_the_maps_of_casting_at_every_pass(monkeypatch):
    """pyramid.cast_weights (bf16 weights stored once, when the backbone is built) against the
    same random draw left in float32 and cast by autocast at every pass: the same maps, bit for bit."""
    def build(cast: bool) -> backbones.Backbone:
        torch.manual_seed(0)
        with monkeypatch.context() as m:
            if not cast:
                m.setattr(pyramid, "cast_weights", lambda module, dtype: None)
            return backbones.load_backbone("efficientnet_lite0", pretrained=False, precision="bf16")

    each, once = build(False), build(True)
    assert any(p.dtype == torch.bfloat16 for p in once.parameters())
    assert not any(p.dtype == torch.bfloat16 for p in each.parameters())
    image = torch.rand(1, 3, 96, 128, generator=torch.Generator().manual_seed(0))
    assert all(torch.equal(a, b) for a, b in zip(each(image), once(image)))


def test_the_ordered_norm_equals_torchs_norm():
    """norms.ordered_norm on a ReLU'd 64-channel map where it takes its fast path
    (norms.ordered_is_exact): torch's Tensor.norm over the channels, bit for bit."""
    feat = torch.randn(64, 240, 320, generator=torch.Generator().manual_seed(0)).relu_()
    assert norms.ordered_is_exact(feat)
    assert torch.equal(norms.ordered_norm(feat), feat.norm(2, 0, keepdim=True))
    assert torch.equal(norms.channel_norm(feat), feat.norm(2, 0, keepdim=True))


def test_bf16_rows_widened_then_divided_equal_dividing_them_directly():
    """cascade.UnitPixels.gather (bf16 rows widened to float32, then divided in place by their
    norms) gives the bits of dividing the bf16 rows by the float32 norms directly, on 60 random
    16 x 16 patches of a 320 x 240 map."""
    gen = torch.Generator().manual_seed(0)
    w, h = 320, 240
    rows = (torch.randn(h * w, 64, generator=gen).relu_() * 3).bfloat16()
    pixel_norms = rows.float().norm(dim=1).clamp_min_(1e-12)
    cells = torch.stack([torch.randint(0, w // 16, (60,), generator=gen),
                         torch.randint(0, h // 16, (60,), generator=gen)], 1)
    unit = UnitPixels(rows, pixel_norms, w)
    index = unit.patch_index(cells, 16)
    direct = torch.div(rows.index_select(0, index), pixel_norms.index_select(0, index)[:, None])
    assert torch.equal(unit.gather(index), direct)


ALLOCATOR_SCRIPT = r"""
import cv2, hashlib, json, torch
from e3cm_bench.ground import devices
from e3cm_bench.matching import norms
from e3cm_bench.matching.cascade import UnitPixels
from e3cm_bench.method.spec import MethodSpec
from e3cm_bench.apps.synth.textures import demo_homography, procedural_scene

torch.manual_seed(0)
matcher = MethodSpec.create("e3cm", "vgg19").build("cpu", pretrained=False)
image0 = procedural_scene((320, 240))
image1 = cv2.warpPerspective(image0, demo_homography((320, 240)), (320, 240), borderMode=cv2.BORDER_REFLECT)

def digest():
    m = matcher.match(image0, image1)
    return len(m), hashlib.sha256(m.keypoints0.tobytes() + m.keypoints1.tobytes() + m.scores.tobytes()).hexdigest()

before = [digest(), digest()]
allocator = devices.keep_freed_memory()
after = [digest(), digest()]  # the second pass of each reuses the pages the first freed
block = torch.ones(50_000_000)  # 200 MB, freed: kept for reuse, and counted as available
del block
print(json.dumps({"allocator": allocator, "again": devices.keep_freed_memory(), "before": before, "after": after,
                  "kept_free": devices.kept_free_bytes()}))
"""


def run_allocator_script(env: dict | None = None) -> dict:
    done = subprocess.run([sys.executable, "-c", ALLOCATOR_SCRIPT], capture_output=True, text=True, check=True,
                          env={**os.environ, **(env or {})})
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.slow  # 7 s in the fast set under a load of about 7 on the shared 2-core machine (docs/development.md, Testing)
def test_keeping_freed_memory_changes_no_match():
    """glibc keeping freed memory (devices.keep_freed_memory, which every run turns on) gives the
    same matches to the bit as the system's allocator (VGG19, random weights, in a fresh process)."""
    if not GLIBC:
        pytest.skip("keep_freed_memory tunes glibc's malloc only; this C library is left as it is")
    out = run_allocator_script({"E3CM_BENCH_ALLOCATOR": ""})
    assert out["allocator"].startswith("glibc, freed memory kept") and out["again"] == out["allocator"]
    assert out["before"][0][0] > 100  # a real set of matches
    assert out["before"][0] == out["before"][1] == out["after"][0] == out["after"][1]
    assert out["kept_free"] >= 200_000_000  # what available_host_memory adds to MemAvailable


@pytest.mark.slow  # 9 s in the fast set under a load of about 7 on the shared 2-core machine (docs/development.md, Testing)
def test_keeping_freed_memory_can_be_turned_off():
    out = run_allocator_script({"E3CM_BENCH_ALLOCATOR": "system"})
    assert out["allocator"] == "system (E3CM_BENCH_ALLOCATOR=system)"
    assert out["before"] == out["after"] and out["kept_free"] == 0
