"""The speed machinery changes no result: decoding ahead, cross-method feature sharing."""

from __future__ import annotations

import csv
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
import yaml

from e3cm_bench.benchmarks import get_benchmark
from e3cm_bench.datasets.base import Pair
from e3cm_bench.images import ImageError
from e3cm_bench.method import MethodSpec
from e3cm_bench.run.stage import MatchOptions, decoded_ahead
from e3cm_bench.runner import run_benchmark, run_methods
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
        assert config["environment"]["allocator"] == "glibc, freed memory kept (M_MMAP_MAX=0, no trim)"

    run_benchmark(hp, tmp_path / "plain", method, root=root, dataset_options={"sequences": ["v_boat"]}, limit=3,
                  options=MatchOptions(feature_cache_mb=0))
    assert "feature_reuse" not in yaml.safe_load((tmp_path / "plain" / "config.yaml").read_text())

    assert_same_arrays(tmp_path / "reuse", tmp_path / "plain")


def test_methods_matched_together_share_maps_and_give_the_same_matches(shared_data, tmp_path, monkeypatch):
    """reproduce's joint stage: e3cm, direct and e3cm-release (one backbone setting) on three
    pairs with four distinct images load the weights once and pass each image through the
    network once between them (4 passes, not 3 x 6), and each method's matches equal those
    of its own run. The normalised maps e3cm and direct make of an image are made once and
    shared too (FeatureCache.derived), and change nothing either."""
    import e3cm_bench.backbones as backbones

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
    from e3cm_bench.runner import match_pair

    matcher = MethodSpec.create("e3cm", "vgg19").build("cpu", pretrained=False)
    need = 6 * matcher.backbone.pyramid_bytes(4000, 6000)
    free = available_memory(matcher.device)
    if free is None or need <= free:
        pytest.skip(f"this machine has {free} bytes free: a 6000 x 4000 pair fits (or memory is unknown)")
    image = np.zeros((4000, 6000, 3), np.uint8)
    with pytest.raises(MemoryError, match=r"--max-side \d+ would fit"):
        match_pair(matcher, image, image)


def test_bench_batch_prints_and_writes_its_figures(tmp_path: Path):
    """scripts/bench_batch.py on a tiny case: one row per backbone, size and precision, with
    the two ways' maps within rounding of each other."""
    out = tmp_path / "batch.csv"
    script = Path(__file__).resolve().parents[1] / "scripts" / "bench_batch.py"
    run = subprocess.run([sys.executable, str(script), "--backbone", "efficientnet_lite0", "--size", "64x48",
                          "--batch", "2", "--images", "3", "--repeat", "1", "--csv", str(out)],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "efficientnet_lite0 64x48 fp32: one by one" in run.stdout
    rows = list(csv.DictReader(out.open()))
    assert len(rows) == 1 and rows[0]["batch"] == "2" and float(rows[0]["largest difference"]) < 1e-4
    assert float(rows[0]["one by one s/image"]) > 0 and float(rows[0]["batched s/image"]) > 0


def test_bench_maps_copy_prints_equal_copies_per_level():
    """scripts/bench_maps_copy.py on a small case whose level 0 (16 x 240 x 320, over 1M
    elements) takes the banded copy: a line per level, each copy equal to torch's bit for bit,
    and the whole pass timed both ways."""
    script = Path(__file__).resolve().parents[1] / "scripts" / "bench_maps_copy.py"
    run = subprocess.run([sys.executable, str(script), "--backbone", "efficientnet_lite0", "--precision", "bf16",
                          "--size", "320x240", "--repeat", "1"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    levels = [line for line in run.stdout.splitlines() if " level " in line]
    assert len(levels) == 5 and all(line.endswith("bit for bit equal: True") for line in levels), run.stdout
    assert "level 0 (16, 240, 320) bfloat16" in levels[0]
    assert "whole pass of one image: plain copy" in run.stdout


def test_bench_weight_cast_prints_equal_maps():
    """scripts/bench_weight_cast.py on a small case: the weights cast once give the maps of
    casting them at every pass, bit for bit."""
    script = Path(__file__).resolve().parents[1] / "scripts" / "bench_weight_cast.py"
    run = subprocess.run([sys.executable, str(script), "--backbone", "efficientnet_lite0", "--size", "128x96",
                          "--repeat", "1"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    line = run.stdout.splitlines()[1]
    assert line.startswith("efficientnet_lite0 bf16 128x96 (") and line.endswith("bit for bit equal: True"), run.stdout


def test_bench_norm_prints_equal_norms():
    """scripts/bench_norm.py on a small map (the banded path taken): equal bit for bit, and the
    allocator it ran with named."""
    script = Path(__file__).resolve().parents[1] / "scripts" / "bench_norm.py"
    run = subprocess.run([sys.executable, str(script), "--size", "320x240", "--repeat", "1"], capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert "; allocator glibc, freed memory kept" in lines[0] or "; allocator system" in lines[0]
    assert lines[1].startswith("320x240: torch norm") and "bit for bit equal: True; fast path taken: True" in lines[1]


def test_bench_gather_prints_equal_gathers():
    """scripts/bench_gather.py on a small map: bf16 rows widened before they are divided give
    the bits of dividing them by the float32 norms directly (cascade.UnitPixels.gather)."""
    script = Path(__file__).resolve().parents[1] / "scripts" / "bench_gather.py"
    run = subprocess.run([sys.executable, str(script), "--size", "320x240", "--patches", "60", "--repeat", "1"],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert "60 patches of 16 x 16 pixels" in lines[0]
    assert lines[1].startswith("320x240: bf16 / float32") and lines[1].endswith("bit for bit equal: True"), run.stdout


ALLOCATOR_SCRIPT = r"""
import cv2, hashlib, json, torch
from e3cm_bench import devices
from e3cm_bench.method import MethodSpec
from e3cm_bench.synth.textures import demo_homography, procedural_scene

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


def test_keeping_freed_memory_can_be_turned_off():
    out = run_allocator_script({"E3CM_BENCH_ALLOCATOR": "system"})
    assert out["allocator"] == "system (E3CM_BENCH_ALLOCATOR=system)"
    assert out["before"] == out["after"] and out["kept_free"] == 0


def test_bench_allocator_alternates_and_matches_equal(tmp_path):
    """scripts/bench_allocator.py on a small pair: both settings timed in one process, the
    matches equal bit for bit, and a CSV row per size."""
    if not GLIBC:
        pytest.skip("bench_allocator.py compares glibc's settings")
    script = Path(__file__).resolve().parents[1] / "scripts" / "bench_allocator.py"
    table = tmp_path / "allocator.csv"
    run = subprocess.run([sys.executable, str(script), "--backbone", "efficientnet_lite0", "--precision", "fp32",
                          "--size", "160x120", "--repeat", "1", "--csv", str(table)], capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stderr
    line = next(line for line in run.stdout.splitlines() if line.startswith("160x120:"))
    assert "pair default" in line and "keep / default" in line and line.endswith("bit for bit equal: True")
    rows = list(csv.reader(table.open()))
    assert rows[0][:2] == ["backbone, precision", "size"] and rows[1][:2] == ["efficientnet_lite0, fp32", "160x120"]
    assert rows[1][8] == "yes"
