"""MatchCache: round trips, empty entries, and resuming after an interrupted run."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from e3cm_bench.storage.cache import BLOCK_PAIRS, MatchCache
from e3cm_bench.ground.matches import Matches


def make_matches(n: int, seed: int = 0) -> Matches:
    rng = np.random.default_rng(seed)
    return Matches(rng.uniform(0, 640, (n, 2)), rng.uniform(0, 480, (n, 2)), rng.uniform(0, 1, n))


def test_round_trip_with_nested_names(tmp_path):
    cache = MatchCache(tmp_path / "sub" / "matches.h5")  # parent folder created on write
    first, second = make_matches(50, seed=1), make_matches(7, seed=2)
    cache.write("v_graffiti/1-2", first, {"size0": (800, 640), "size1": (800, 600), "seconds": 0.25, "method": "sift"})
    cache.write("kitti00_seq/000100--000103", second)

    assert "v_graffiti/1-2" in cache.names() and "kitti00_seq/000100--000103" in cache.names()
    assert "v_graffiti/1-3" not in cache.names() and "v_graffiti" not in cache.names()
    assert cache.names() == ["kitti00_seq/000100--000103", "v_graffiti/1-2"]

    back = cache.read("v_graffiti/1-2")
    for name in ("keypoints0", "keypoints1", "scores"):
        np.testing.assert_array_equal(getattr(back, name), getattr(first, name))
        assert getattr(back, name).dtype == np.float32
    assert back.keypoints0.shape == (50, 2) and back.scores.shape == (50,)
    np.testing.assert_array_equal(back.info["size0"], [800, 640])
    assert back.info["seconds"] == 0.25 and isinstance(back.info["seconds"], float)
    assert back.info["method"] == "sift"
    assert "complete" not in back.info
    assert cache.read("kitti00_seq/000100--000103").info == {}


def test_zero_matches(tmp_path):
    cache = MatchCache(tmp_path / "matches.h5")
    cache.write("v_boat/1-6", Matches(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0)))
    back = cache.read("v_boat/1-6")
    assert len(back) == 0
    assert back.keypoints0.shape == (0, 2) and back.keypoints1.shape == (0, 2) and back.scores.shape == (0,)


def test_write_replaces_an_existing_entry(tmp_path):
    cache = MatchCache(tmp_path / "matches.h5")
    cache.write("a/b", make_matches(20), {"old": 1})
    cache.write("a/b", make_matches(3, seed=5), {"new": 2})
    back = cache.read("a/b")
    assert len(back) == 3 and back.info == {"new": 2}


def test_entry_without_complete_mark_is_absent(tmp_path):
    path = tmp_path / "matches.h5"
    with h5py.File(path, "w") as file:
        group = file.create_group("v_boat/1-2")
        group.create_dataset("keypoints0", data=np.zeros((4, 2), np.float32))
    cache = MatchCache(path)
    assert "v_boat/1-2" not in cache.names()
    assert cache.names() == []
    with pytest.raises(KeyError, match="v_boat/1-2"):
        cache.read("v_boat/1-2")


def test_interrupted_run_resumes(tmp_path):
    path = tmp_path / "matches.h5"
    cache = MatchCache(path)
    cache.write("v_boat/1-2", make_matches(10))
    cache.write("v_boat/1-3", make_matches(11))
    # A run killed while writing the third pair: its group exists, half filled, unmarked.
    with h5py.File(path, "a") as file:
        group = file.create_group("v_boat/1-4")
        group.create_dataset("keypoints0", data=np.zeros((12, 2), np.float32))
        group.create_dataset("keypoints1", data=np.zeros((12, 2), np.float32))
    assert cache.names() == ["v_boat/1-2", "v_boat/1-3"]
    assert "v_boat/1-4" not in cache.names()

    # The next run skips what is done and rewrites the interrupted pair.
    cache.write("v_boat/1-4", make_matches(12, seed=3))
    assert cache.names() == ["v_boat/1-2", "v_boat/1-3", "v_boat/1-4"]
    assert len(cache.read("v_boat/1-4")) == 12


def test_missing_file_reads_as_empty(tmp_path):
    cache = MatchCache(tmp_path / "absent.h5")
    assert cache.names() == [] and "x/y" not in cache.names()
    assert not cache.path.exists()


def test_invalid_names_rejected(tmp_path):
    cache = MatchCache(tmp_path / "matches.h5")
    for bad in ("", "/abs", "a//b", "a/../b", "trailing/"):
        with pytest.raises(ValueError, match="invalid pair name"):
            cache.write(bad, make_matches(1))


def test_a_foreign_file_is_a_damaged_block_left_untouched(tmp_path):
    path = tmp_path / "matches.h5"
    path.write_text("not an hdf5 file\n")
    cache = MatchCache(path)
    assert cache.names() == [] and cache.damaged == [path]
    with pytest.raises(KeyError):
        cache.read("a/b")
    cache.write("a/b", make_matches(2))  # goes to a new block
    assert cache.names() == ["a/b"] and cache.blocks() == [path, tmp_path / "matches.001.h5"]
    assert path.read_text() == "not an hdf5 file\n"  # left untouched


def test_a_damaged_block_costs_only_its_own_pairs(tmp_path):
    path = tmp_path / "matches.h5"
    cache = MatchCache(path)
    names = [f"scene/p{i:03d}" for i in range(2 * BLOCK_PAIRS + 20)]
    for name in names:
        cache.write(name, make_matches(500))
    blocks = cache.blocks()
    assert [p.name for p in blocks] == ["matches.h5", "matches.001.h5", "matches.002.h5"]
    # A copy cut short: 2 KiB off the end of the middle block.
    content = blocks[1].read_bytes()
    blocks[1].write_bytes(content[:-2048])
    fresh = MatchCache(path)
    readable = fresh.names()
    assert fresh.damaged == [blocks[1]]
    # The pairs HDF5 still reads whole from the cut block are kept; the lost ones are its own only.
    lost = sorted(set(names) - set(readable))
    assert 0 < len(lost) < BLOCK_PAIRS and set(lost) <= set(names[BLOCK_PAIRS:2 * BLOCK_PAIRS])
    assert fresh.recovered == {blocks[1]: BLOCK_PAIRS - len(lost)}
    for name in (names[-1], next(n for n in names[BLOCK_PAIRS:] if n not in lost)):
        np.testing.assert_array_equal(fresh.read(name).keypoints0, cache.read(name).keypoints0)
    # Matching the lost pairs again writes them to a new block after the damaged one.
    for name in lost:
        fresh.write(name, make_matches(500))
    assert MatchCache(path).names() == sorted(names)
    with h5py.File(blocks[2]) as last:  # the last block had room; the damaged one takes no pair
        assert all(name in last for name in lost)
    assert blocks[1].read_bytes() == content[:-2048]  # the damaged block is left as it is


def test_unstorable_attribute_names_the_key(tmp_path):
    cache = MatchCache(tmp_path / "matches.h5")
    with pytest.raises(TypeError, match="'levels'"):
        cache.write("a/b", make_matches(2), {"levels": {"coarse": 1}})
    assert "a/b" not in cache.names()
    with pytest.raises(ValueError, match="reserved"):
        cache.write("a/b", make_matches(2), {"complete": 1})
