"""The feature cache: memory budget, spill to disk, maps held in bf16; none of it changes a match."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
import torch
import yaml

from e3cm_bench.benchmarks import get_benchmark
from e3cm_bench.storage.cache import MatchCache
from e3cm_bench.matchers.feature_cache import FeatureCache, compact
from e3cm_bench.matchers.spill import SpillStore
from e3cm_bench.method.spec import MethodSpec
from e3cm_bench.ground.images import load_image
from e3cm_bench.storage import RunFolder
from e3cm_bench.pipeline.pair import matcher_input
from e3cm_bench.pipeline.match_options import MatchOptions
from e3cm_bench.pipeline.runner import run_benchmark
from helpers import assert_same_arrays, replay_stage

MiB = 2**20


def pyramid(seed: int, floats: int = MiB // 4) -> list[torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    return [torch.randn(floats // 2, generator=gen), torch.randn(4, floats // 8, generator=gen)]


def test_memory_and_disk_stay_within_their_bounds_and_give_back_the_same_maps(tmp_path):
    spill = SpillStore(tmp_path / "spill", max_mb=3)
    cache = FeatureCache(2.5, spill)  # two of the 0.75 MiB pyramids below... and a half
    made = {}
    for step in range(40):
        key = f"image{step % 7}"
        maps = cache.get(key)
        if maps is None:
            maps = pyramid(step % 7)
            cache.put(key, maps)
        made.setdefault(key, maps)
        assert all(torch.equal(a, b) for a, b in zip(maps, made[key]))
        assert cache.bytes <= cache.max_bytes and spill.bytes <= spill.max_bytes
        assert sum(f.stat().st_size for f in spill.folder.glob("*.pt")) <= spill.max_bytes + 4096 * len(spill.sizes)
    stats = cache.stats()
    assert stats["read_from_disk"] > 0 and stats["disk_full"] > 0  # both bounds were reached
    assert stats["distinct_images"] == 7 and stats["peak_memory_mb"] <= 2.5
    cache.close()
    assert not spill.folder.exists()


def test_done_with_drops_an_images_maps_from_memory_and_disk(tmp_path):
    spill = SpillStore(tmp_path / "spill", max_mb=10)
    cache = FeatureCache(1.0, spill)  # one pyramid in memory, the other on disk
    cache.pair_files = ("a.jpg", "b.jpg")
    for which, key in enumerate(("A", "B")):
        cache.belongs_to(key, which)
        cache.put(key, pyramid(which))
    assert "A" in spill and "B" in cache.entries
    cache.done_with("a.jpg")
    assert "A" not in spill and not list(spill.folder.glob("*.pt"))
    cache.done_with("b.jpg")
    assert not cache.entries and cache.bytes == 0
    # maps shared by two files (the same content under two names) stay while either has pairs left
    cache.pair_files = ("c.jpg", "d.jpg")
    cache.belongs_to("C", 0)
    cache.belongs_to("C", 1)
    cache.put("C", pyramid(3))
    cache.done_with("c.jpg")
    assert "C" in cache.entries
    cache.done_with("d.jpg")
    assert "C" not in cache.entries


def _replay(cache: FeatureCache, files_in_order: list[tuple[str, str]]) -> None:
    """The match stage's use of the cache (helpers.replay_stage), file name = key here."""
    replay_stage(cache, files_in_order, lambda f: pyramid(ord(f[0])))


def test_with_the_order_known_the_cache_keeps_what_is_needed_soonest():
    """A B, C B, then A D: with room for two pyramids, least recently used would drop A when C
    comes (4 + 1 passes); told the order, the cache keeps A and B, which come again sooner
    than C, which is needed by its pair alone: each image passes once."""
    order = [("a", "b"), ("c", "b"), ("a", "d")]
    planned = FeatureCache(2.5)  # two 1 MiB pyramids
    _replay(planned, order)
    assert planned.misses == 4
    lru = FeatureCache(2.5)
    for files in order:
        for f in files:
            if lru.get(f) is None:
                lru.put(f, pyramid(ord(f)))
    assert lru.misses == 5
    # a pyramid the pair being matched has yet to be handed stays (here, a pair of an image
    # with itself: out would go a or b, needed later, not c)
    self_pair = FeatureCache(2.5)
    _replay(self_pair, [("a", "b"), ("c", "c"), ("a", "b")])
    assert self_pair.misses == 4


def test_a_full_spill_keeps_what_is_needed_sooner(tmp_path):
    """Memory for one pyramid, disk for one: when the disk is full, the pyramid needed later is
    the one dropped (it is computed again), and nothing without a pair left is written."""
    spill = SpillStore(tmp_path / "spill", max_mb=1.2)
    cache = FeatureCache(1.2, spill)  # one 1 MiB pyramid in each
    # after the first pair, b waits on disk for pair 3; at pair 1, c (needed at pair 2) takes
    # its place, and b is computed again at pair 3
    order = [("a", "b"), ("c", "a"), ("c", "d"), ("b", "e"), ("a", "f")]
    _replay(cache, order)
    assert spill.dropped == 1 and spill.refused == 0 and spill.reads == 1
    assert cache.misses == 7  # 6 images, b twice
    assert cache.stats()["dropped_from_disk"] == spill.dropped
    cache.close()
    assert not spill.folder.exists()


def test_products_of_an_images_maps_are_made_once_and_go_first_when_memory_is_short():
    """derived(): computed once per image while its maps are held, counted in the budget, the
    first to go when memory is short (the maps stay), and gone with the maps."""
    cache = FeatureCache(2.5)  # two 1 MiB pyramids, and half a pyramid to spare
    level0 = pyramid(1)[0]
    cache.put("a", pyramid(1))
    calls = []

    def unit():
        calls.append(1)
        return torch.nn.functional.normalize(level0, dim=0)

    first = cache.derived("a", "unit:0", unit)
    assert cache.derived("a", "unit:0", unit) is first and len(calls) == 1 and cache.products_reused == 1
    assert cache.bytes == 1.5 * MiB  # the pyramid and its 0.5 MiB product
    cache.put("b", pyramid(2))  # 2.5 MiB: fits with the product
    assert "a" in cache.products
    cache.put("c", pyramid(3))  # short: the product goes first, then a pyramid
    assert not cache.products and len(cache.entries) == 2 and cache.bytes <= cache.max_bytes
    cache.derived("c", "unit:0", lambda: torch.zeros(MiB // 8))
    cache.forget("c")
    assert not cache.products and cache.bytes == MiB
    # not held in memory: computed each time, kept nowhere
    assert cache.derived("zz", "unit:0", unit) is not first and len(calls) == 2


def test_maps_held_in_bf16_come_back_as_the_float32_maps_without_widening_each_time():
    gen = torch.Generator().manual_seed(0)
    maps = [torch.randn(8, 16, 16, generator=gen).to(torch.bfloat16).float() for _ in range(2)]
    cache = FeatureCache(1.0, compact_dtype=torch.bfloat16)
    cache.put("k", maps)
    assert all(m.dtype == torch.bfloat16 for m in cache.entries["k"])
    got = cache.get("k")
    assert got is cache.get("k") and all(torch.equal(a, b) and a.dtype == torch.float32 for a, b in zip(got, maps))


def test_maps_computed_in_bf16_are_held_in_bf16_exactly_and_others_are_not():
    gen = torch.Generator().manual_seed(0)
    from_bf16 = torch.randn(8, 16, 16, generator=gen).to(torch.bfloat16).float()
    full = torch.randn(8, 16, 16, generator=gen)
    exact = {}
    held = compact([from_bf16, full], torch.bfloat16, exact)
    assert held[0].dtype == torch.bfloat16 and held[1].dtype == torch.float32 and exact == {0: True, 1: False}
    cache = FeatureCache(1.0, compact_dtype=torch.bfloat16)
    cache.put("k", [from_bf16, full])
    # held: the narrow level in 2 bytes, the other as it is; beside them (a product, the first
    # to go when memory is short) the float32 level in hand, so that it is not widened again
    assert sum(m.numel() * m.element_size() for m in cache.entries["k"]) == from_bf16.numel() * 2 + full.numel() * 4
    assert cache.bytes == from_bf16.numel() * 2 + full.numel() * 4 + from_bf16.numel() * 4
    back = cache.get("k")
    assert back[0].dtype == torch.float32 and torch.equal(back[0], from_bf16) and torch.equal(back[1], full)


@pytest.mark.slow  # 24 s (fp32) and 15 s (bf16) in the fast set under a load of about 7 on the shared 2-core machine (docs/development.md, Testing)
@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_spilling_to_disk_passes_each_image_once_and_changes_no_match(shared_data, tmp_path, precision):
    """v_boat's five pairs share image 1; with memory for less than one pyramid (bf16 maps held
    in bf16: half the float32 size), image 1 waits in the run folder between its pairs and
    comes back: 6 passes for 6 images, and the matches are byte-identical to those of a run
    without any reuse. Nothing is left on disk. (With memory for one, image 1 would stay in
    memory: the cache keeps what is needed soonest, and the others have no pair left.)"""
    options = {} if precision == "fp32" else {"precision": precision}
    method = MethodSpec.create("direct", "efficientnet_lite0", max_side=320, options=options)
    hp = get_benchmark("hpatches")
    root = shared_data / "hpatches-sequences-release"
    dataset = hp.load_dataset(root, sequences=["v_boat"])
    one = method.build("cpu").backbone.pyramid_bytes(240, 320) / MiB  # float32 bytes of one pyramid
    budget = one * (0.8 if precision == "fp32" else 0.4)  # bf16 maps are held in 2 bytes
    run_benchmark(hp, tmp_path / "spill", method, dataset=dataset, options=MatchOptions(feature_cache_mb=budget))
    reuse = yaml.safe_load((tmp_path / "spill" / "config.yaml").read_text())["feature_reuse"]
    assert reuse["backbone_passes"] == 6 == reuse["distinct_images"] and reuse["passes_per_image"] == 1.0
    assert reuse["read_from_disk"] == 4 and reuse["peak_memory_mb"] == 0 and reuse["images_alive_at_most"] == 2
    # written once and read in place (memory cannot hold it); the others have no pair left to wait for
    assert reuse["written_to_disk"] == 1
    assert not (RunFolder(tmp_path / "spill").spill_dir).exists()
    run_benchmark(hp, tmp_path / "plain", method, dataset=dataset, options=MatchOptions(feature_cache_mb=0))
    assert_same_arrays(tmp_path / "spill", tmp_path / "plain")


@pytest.mark.slow  # 23 s (short) and 15 s (default) in the fast set under a load of about 7 on the shared 2-core machine (docs/development.md, Testing)
@pytest.mark.parametrize("memory", ["default", "short"])
def test_backbone_passes_batched_ahead_pass_each_image_once_and_change_no_match(shared_data, tmp_path, memory):
    """--backbone-batch 4 on v_boat's five pairs (six images): the first pair's images go
    through the network with the coming pairs' images, four at a time; every image passes
    once, and the matches are byte-identical to those of a run without any reuse where the
    batched pass gives each image its own pass's maps bit for bit (checked first: it does at
    this size on this project's CPU; the kernel library picks algorithms by shape), else the
    same pairs with about the same matches. With memory for less than one pyramid the maps
    computed ahead wait on disk instead."""
    method = MethodSpec.create("direct", "efficientnet_lite0", max_side=320)
    hp = get_benchmark("hpatches")
    dataset = hp.load_dataset(shared_data / "hpatches-sequences-release", sequences=["v_boat"])
    h, w = matcher_input(load_image(dataset.pairs[0].image0), 0, 320, "shrink")[0].shape[:2]
    backbone = method.build("cpu").backbone
    images = torch.rand(4, 3, h, w, generator=torch.Generator().manual_seed(0))
    exact = all(torch.equal(a, b) for i, maps in enumerate(backbone.forward_batch(images))
                for a, b in zip(maps, backbone(images[i:i + 1])))
    budget = None if memory == "default" else 0.8 * method.build("cpu").backbone.pyramid_bytes(240, 320) / MiB
    run_benchmark(hp, tmp_path / "batched", method, dataset=dataset, options=MatchOptions(feature_cache_mb=budget, backbone_batch=4))
    reuse = yaml.safe_load((tmp_path / "batched" / "config.yaml").read_text())["feature_reuse"]
    assert reuse["backbone_batch"] == 4 and reuse["largest_batch"] == 4
    assert reuse["backbone_passes"] == 6 == reuse["distinct_images"]
    if memory == "short":
        assert reuse["read_from_disk"] >= 5  # each image computed ahead came back from disk
    run_benchmark(hp, tmp_path / "plain", method, dataset=dataset, options=MatchOptions(feature_cache_mb=0))
    if exact:
        assert_same_arrays(tmp_path / "batched", tmp_path / "plain")
    else:
        batched, plain = MatchCache(tmp_path / "batched" / "matches.h5"), MatchCache(tmp_path / "plain" / "matches.h5")
        assert batched.names() == plain.names()
        for name in plain.names():
            n, m = len(batched.read(name).keypoints0), len(plain.read(name).keypoints0)
            assert abs(n - m) <= 0.02 * m + 2, (name, n, m)
    plain = yaml.safe_load((tmp_path / "plain" / "config.yaml").read_text())
    assert "feature_reuse" not in plain or plain["feature_reuse"].get("batches_run", 0) == 0


PEAK_SCRIPT = """
import json, sys
from pathlib import Path
import cv2, numpy as np
from rich.console import Console
import e3cm_bench.pipeline.stage as stage
from e3cm_bench.pipeline.match_options import MatchOptions
from e3cm_bench.storage.cache import MatchCache
from e3cm_bench.datasets.base import Pair
from e3cm_bench.method.spec import MethodSpec
from e3cm_bench.apps.synth.textures import procedural_scene

import ctypes
libc = ctypes.CDLL("libc.so.6")

def resident_mb():
    libc.malloc_trim(0)  # freed memory back to the system first, so that what is counted is what is held
    return int(open("/proc/self/statm").read().split()[1]) * 4096 / 2**20

# the resident memory after each pair: what the process holds between pairs (the cache among
# it), without the network's transient activations, which dwarf a few pyramids at their peak
after = []
match_one = stage._match_one
def measured(*args, **kwargs):
    match_one(*args, **kwargs)
    after.append(resident_mb())
stage._match_one = measured

folder, budget = Path(sys.argv[1]), float(sys.argv[2])
paths = []
for i in range(8):
    path = folder / f"{i}.png"
    if not path.exists():
        cv2.imwrite(str(path), procedural_scene((640, 480), seed=i))
    paths.append(path)
edges = [(i, (i + 1) % 8) for i in range(8)] + [(i, (i + 3) % 8) for i in range(8)]
pairs = [Pair(f"{a}-{b}", paths[a], paths[b]) for a, b in edges]
method = MethodSpec.create("direct", "efficientnet_lite0")
out = folder / f"run{budget}"
out.mkdir()
stats = stage.match_stage(method, pairs, MatchCache(out / "matches.h5"), "cpu", Console(quiet=True), options=MatchOptions(feature_cache_mb=budget,
                           spill_mb=0))
print(json.dumps({"peak_mb": max(after), "reuse": stats.get("feature_reuse")}))
"""


@pytest.mark.slow  # a real run's peak memory measured in a fresh process: about a minute
def test_the_cache_never_holds_more_than_its_budget_peak_rss(tmp_path):
    """Resident memory of the match stage after each pair (max over the pairs), each run in a
    fresh process, on 8 images of 640 x 480 and 16 pairs (Lite0): with a budget of two
    pyramids it stays within the budget (plus a margin for the allocator) of the same figure
    without any cache; with room for all eight it does not, so the measurement sees what a
    cache holds. (Peak RSS over the whole run does not: one backbone pass's activations,
    about 2.6 GB here, dwarf eight 32 MiB pyramids.)"""
    def peak(budget: float) -> dict:
        # glibc: every large block mmapped and unmapped when freed (no dynamic threshold that
        # moves freed maps to the heap, where they stay resident whatever holds them)
        env = {**os.environ, "MALLOC_MMAP_THRESHOLD_": "131072"}
        done = subprocess.run([sys.executable, "-c", PEAK_SCRIPT, str(tmp_path), str(budget)], capture_output=True,
                              text=True, check=True, env=env)
        return json.loads(done.stdout.strip().splitlines()[-1])

    one = MethodSpec.create("direct", "efficientnet_lite0").build("cpu").backbone.pyramid_bytes(480, 640) / MiB
    margin = 0.75 * one
    none, two, all_eight = peak(0), peak(2.01 * one), peak(9 * one)
    print(f"one pyramid {one:.1f} MiB; resident after a pair, at most: no cache {none['peak_mb']:.0f} MiB, "
          f"two pyramids {two['peak_mb']:.0f} MiB, eight {all_eight['peak_mb']:.0f} MiB")
    assert two["reuse"]["backbone_passes"] > 8  # the budget was binding
    assert two["reuse"]["peak_memory_mb"] <= 2.01 * one
    assert two["peak_mb"] <= none["peak_mb"] + 2.01 * one + margin, (none, two)
    assert all_eight["peak_mb"] > none["peak_mb"] + 2.01 * one + margin, (none, all_eight)


def test_level0_rows_of_a_pass_are_kept_with_its_maps_and_change_no_match(shared_data, monkeypatch):
    """e3cm (top-8) reads level 0 by pixels: a bf16 backbone's own channels-last rows are kept
    beside the image's maps in the cache (in bf16) and read by its later pairs, and the
    matches are bit for bit those of rows copied out of the float32 map."""
    folder = shared_data / "hpatches-sequences-release" / "v_boat"
    images = [matcher_input(load_image(folder / f"{k}.ppm"), 0, 320, "shrink")[0] for k in (1, 2, 3)]
    method = MethodSpec.create("e3cm", "efficientnet_lite0", max_side=320, options={"precision": "bf16"})
    torch.manual_seed(0)
    cached = method.build("cpu", pretrained=False)
    torch.manual_seed(0)
    copied = method.build("cpu", pretrained=False)
    assert cached.wants_pixel_rows
    monkeypatch.setattr(copied, "wants_pixel_rows", False)  # the rows are copied from the float32 map
    cached.reuse_features(1024)
    for second in (1, 2):
        got, want = cached.match(images[0], images[second]), copied.match(images[0], images[second])
        assert got.info["counts_after"][4] >= 8  # the confidence score ran
        for a, b in ((got.keypoints0, want.keypoints0), (got.keypoints1, want.keypoints1), (got.scores, want.scores)):
            assert a.tobytes() == b.tobytes()
        rows = cached.feature_cache.products[cached.image_key(images[0])]["pixel_rows:0"]
        assert rows.dtype == torch.bfloat16
        if second == 2:  # image 0 came from the cache: its rows too, not a copy of its map
            assert cached.image_product(0, "pixel_rows:0", lambda: pytest.fail("rows copied again")) is rows


def test_an_image_made_inside_a_pair_is_passed_not_kept(shared_data):
    """e3cm-plus warps B by its stage-0 homography (and again to realign): that image is no file
    of the stage's plan, so nothing would ever release its maps, and they piled up until the
    budget (half the memory) was full: the near-8 GB peaks of issue 68. While a pair of the plan
    is matched, such an image is passed through the network and not held; the pair's own
    images are held as before, and the matches are those of a matcher without a cache."""
    folder = shared_data / "hpatches-sequences-release" / "v_graffiti"
    images = [matcher_input(load_image(folder / f"{k}.ppm"), 0, 480, "shrink")[0] for k in (1, 4)]
    method = MethodSpec.create("e3cm-plus", "efficientnet_lite0", max_side=480, options={"prewarp": True})
    cached, plain = method.build("cpu"), method.build("cpu")  # Lite0's weights ship with the package
    cached.reuse_features(1024)
    cache = cached.feature_cache
    cache.plan([("1.ppm", "4.ppm")])
    cache.at(0, ("1.ppm", "4.ppm"))
    got, want = cached.match(*images), plain.match(*images)
    assert got.keypoints0.tobytes() == want.keypoints0.tobytes() and got.keypoints1.tobytes() == want.keypoints1.tobytes()
    assert got.info["prewarp"] == "warped"  # the pair went through a warped B
    assert set(cache.entries) == {cached.image_key(image) for image in images}
