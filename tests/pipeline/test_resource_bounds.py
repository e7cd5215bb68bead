"""Resources and bounds: a full disk loses nothing, hostile configs and images are
bounded, `check` never passes silently, every bad input is one line.

Real processes where the behaviour depends on them (a small tmpfs for a full disk, a killed
parent for its workers, memory and time limits for hostile YAML).
"""

from __future__ import annotations

import errno
import os
import shutil
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import e3cm_bench.storage.cache as cache_module
from e3cm_bench.storage.cache import DiskFullError, MatchCache
from e3cm_bench.ground.matches import Matches
from helpers import invoke, one_line_error


def cli(*args, timeout: float = 900, **kwargs) -> subprocess.CompletedProcess:
    """The real command in its own process."""
    return subprocess.run([sys.executable, "-m", "e3cm_bench.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, **kwargs)


# Runs the command as its child and prints that child's peak resident memory (KiB) on stdout's last line.
PEAK = """
import resource, subprocess, sys
result = subprocess.run([sys.executable, "-m", "e3cm_bench.cli", *sys.argv[1:]], stderr=subprocess.PIPE, text=True)
sys.stderr.write(result.stderr)
print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
sys.exit(result.returncode)
"""


def cli_peak(*args, timeout: float = 120) -> tuple[subprocess.CompletedProcess, int]:
    """The command, and its peak resident memory in bytes."""
    result = subprocess.run([sys.executable, "-c", PEAK, *map(str, args)], capture_output=True, text=True, timeout=timeout)
    return result, int(result.stdout.strip().splitlines()[-1]) * 1024


def error_lines(result: subprocess.CompletedProcess) -> list[str]:
    return [line for line in result.stderr.splitlines() if line.strip()]


def matches(seed: int, n: int = 300) -> Matches:
    rng = np.random.default_rng(seed)
    return Matches(rng.random((n, 2), np.float32) * 500, rng.random((n, 2), np.float32) * 500, rng.random(n, np.float32), {})


# --------------------------------------------------------------------------- 1. a full disk


@pytest.mark.parametrize("fail_at", ["write", "fsync", "replace"])
def test_enospc_at_each_write_position_leaves_every_earlier_pair_readable(tmp_path, monkeypatch, fail_at):
    """The cache's writer raising ENOSPC at each step of a write: the earlier pairs read back
    byte-identical, the block file is unchanged, no temporary file is left, and the pair
    written after space is freed joins them."""
    cache = MatchCache(tmp_path / "matches.h5")
    for i in range(5):
        cache.write(f"s/{i}", matches(i), {"n": i})
    before = {p.name: p.read_bytes() for p in cache.blocks()}

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    with monkeypatch.context() as patch:
        if fail_at == "write":
            real_create_new = cache_module.create_new

            class FullFile:
                def __init__(self, f):
                    self.f = f

                def __enter__(self):
                    return self

                def __exit__(self, *exc):
                    self.f.close()

                def write(self, data):
                    self.f.write(bytes(data)[: len(data) // 2])
                    full()

            # the block's temporary is created through files.create_new (O_EXCL | O_NOFOLLOW)
            patch.setattr(cache_module, "create_new", lambda path: FullFile(real_create_new(path)))
        elif fail_at == "fsync":
            patch.setattr(cache_module.os, "fsync", full)
        else:
            patch.setattr(cache_module.os, "replace", full)
        with pytest.raises(OSError) as error:
            cache.write("s/5", matches(5), {"n": 5})
        assert error.value.errno == errno.ENOSPC
    assert {p.name: p.read_bytes() for p in cache.blocks()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["matches.h5"]  # no temporary left behind
    fresh = MatchCache(tmp_path / "matches.h5")
    assert fresh.names() == [f"s/{i}" for i in range(5)] and not fresh.damaged
    for i in range(5):
        np.testing.assert_array_equal(fresh.read(f"s/{i}").keypoints0, matches(i).keypoints0)
    fresh.write("s/5", matches(5), {"n": 5})
    assert MatchCache(tmp_path / "matches.h5").names() == [f"s/{i}" for i in range(6)]


def test_too_little_free_space_is_refused_before_the_write(tmp_path, monkeypatch):
    cache = MatchCache(tmp_path / "matches.h5")
    cache.write("a", matches(0))
    before = (tmp_path / "matches.h5").read_bytes()
    monkeypatch.setattr(cache_module.shutil, "disk_usage", lambda path: shutil._ntuple_diskusage(10 << 20, 10 << 20, 4096))
    with pytest.raises(DiskFullError, match=rf"{tmp_path}: not enough free disk space \(4.0 KiB free, about .* needed"):
        cache.write("b", matches(1))
    assert (tmp_path / "matches.h5").read_bytes() == before


@pytest.fixture
def small_disk(tmp_path):
    """A 700 KiB tmpfs (root and mount(8) needed; skipped elsewhere); unmounted after."""
    folder = tmp_path / "small"
    folder.mkdir()
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting a small tmpfs needs root")
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=700k", "tmpfs", str(folder)], capture_output=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({mounted.stderr.decode().strip()})")
    yield folder
    subprocess.run(["umount", "-l", str(folder)], capture_output=True)


@pytest.mark.slow  # 42 s alone on a loaded 2-core machine (docs/development.md, Testing)
def test_a_run_on_a_full_disk_ends_in_one_line_and_resumes_every_complete_pair(shared_data, small_disk):
    """SIFT on the shared HPatches pairs into a 700 KiB filesystem: the run stops with one line
    (no crash, no HDF5 traceback), the pairs written before are intact, and after the space
    grows the rerun matches only the pairs that were missing."""
    out = small_disk / "run"
    args = ["hpatches", "--root", shared_data / "hpatches-sequences-release", "--out", out, "--matcher", "sift",
            "--sequences", "v_boat", "--sequences", "v_graffiti"]
    first = cli(*args)
    lines = error_lines(first)
    assert first.returncode == 2, first.stderr[-2000:]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "free" in lines[0] and "Traceback" not in first.stderr
    kept = MatchCache(out / "matches.h5")
    names = kept.names()
    assert not kept.damaged and 0 < len(names) < 10
    saved = {name: kept.read(name).keypoints0.copy() for name in names}
    subprocess.run(["mount", "-o", "remount,size=64m", str(small_disk)], check=True)
    second = cli(*args)
    assert second.returncode == 0, second.stderr[-2000:]
    assert f"10 pairs, {len(names)} already in" in " ".join(second.stdout.split())
    final = MatchCache(out / "matches.h5")
    assert len(final.names()) == 10
    for name, keypoints in saved.items():
        np.testing.assert_array_equal(final.read(name).keypoints0, keypoints)


# --------------------------------------------------------------------------- 2. workers


def test_workers_beyond_the_machine_are_one_line_and_start_nothing(shared_data, tmp_path):
    line = one_line_error(invoke("hpatches", "--root", shared_data / "hpatches-sequences-release", "--out", tmp_path / "w",
                                 "--matcher", "sift", "--workers", 1000))
    assert "--workers 1000: this machine holds at most" in line and "cores" in line
    assert not (tmp_path / "w").exists()


def test_workers_die_with_their_parent(tmp_path):
    """A parent killed with SIGKILL (no chance to clean up) takes its pool's workers with it."""
    code = """
import os, time
from e3cm_bench.pipeline.launch import worker_pool
pool = worker_pool(2)
futures = [pool.submit(time.sleep, 120) for _ in range(2)]
time.sleep(3)
print(" ".join(str(pid) for pid in pool._processes), flush=True)
time.sleep(120)
"""
    parent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    workers = [int(pid) for pid in parent.stdout.readline().split()]
    assert len(workers) == 2

    def alive(pid):
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        status = Path(f"/proc/{pid}/status")
        return not (status.exists() and "State:\tZ" in status.read_text())

    assert all(alive(pid) for pid in workers)
    parent.kill()
    parent.wait()
    deadline = time.time() + 20
    while time.time() < deadline and any(alive(pid) for pid in workers):
        time.sleep(0.2)
    assert not any(alive(pid) for pid in workers)


# --------------------------------------------------------------------------- 3. check


@pytest.fixture(scope="module")
def sift_run(shared_data, tmp_path_factory):
    out = tmp_path_factory.mktemp("check") / "sift"
    result = invoke("hpatches", "--root", shared_data / "hpatches-sequences-release", "--out", out, "--matcher", "sift",
                    "--sequences", "v_boat", "--limit", 2)
    assert result.exit_code == 0
    baseline = out.parent / "baseline.csv"
    assert invoke("check", out, "--baseline", baseline, "--update").exit_code == 0
    return out, baseline


def test_check_refuses_what_would_let_a_regression_pass(sift_run, tmp_path):
    out, baseline = sift_run
    table = pd.read_csv(baseline)
    metrics = [c for c in table.columns if c not in ("benchmark", "method", "environment")]
    assert invoke("check", out, "--baseline", baseline).exit_code == 0
    cases = []
    nan = table.copy()
    nan[metrics] = np.nan
    cases.append((nan, [], f"{metrics[0]} of sift on hpatches is empty or NaN while the run measures it"))
    bare = table[["benchmark", "method"]]
    cases.append((bare, [], "holds no metric column"))
    text = table.astype(object)
    text.loc[0, metrics[1]] = "abc"
    cases.append((text, [], f"{metrics[1]} of sift on hpatches is 'abc', not a number"))
    cases.append((table.drop(columns=["mma@3"]), ["--tolerance", "mma@3=0.1"], "has no column 'mma@3', which --tolerance asks to check"))
    for number, (frame, extra, says) in enumerate(cases):
        path = tmp_path / f"baseline{number}.csv"
        frame.to_csv(path, index=False)
        line = one_line_error(invoke("check", out, "--baseline", path, *extra))
        assert str(path) in line and says in line, line
    for tolerance in ("mma@3=nan", "mma@3=-1", "mma@3=inf"):
        line = one_line_error(invoke("check", out, "--baseline", baseline, "--tolerance", tolerance))
        assert "tolerance must be a finite number >= 0" in line


# --------------------------------------------------------------------------- 4. hostile YAML


BOMB = "".join(f"l{i}: &l{i} [" + ", ".join([f"*l{i - 1}" if i else '"lol"'] * 9) + "]\n" for i in range(10))


@pytest.mark.parametrize("name, text, says", [
    ("bomb", BOMB, "aliases (*name) are not accepted (line 2)"),
    ("deep", "methods: " + "[" * 100_000 + "]" * 100_000 + "\n", "nested deeper than 32 levels"),
    ("huge", "# " + "x" * (50 << 20) + "\n", "bytes, over the 1048576 a experiment config may hold"),
])
def test_hostile_yaml_is_one_line_in_bounded_time_and_memory(tmp_path, name, text, says):
    config = tmp_path / f"{name}.yaml"
    config.write_text(text)
    started = time.perf_counter()
    result, peak = cli_peak("reproduce", config, "--out", tmp_path / "out")
    seconds = time.perf_counter() - started
    lines = error_lines(result)
    assert result.returncode == 2 and len(lines) == 1, result.stderr[-2000:]
    assert str(config) in lines[0] and says in lines[0], lines[0]
    assert seconds < 60 and peak < 1.5 * 2**30, (seconds, peak / 2**30)
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------- 5. silently wrong results


def test_a_pair_without_translation_is_bad_input(shared_data, tmp_path):
    """T_0to1 with zero translation (its direction, half the pose error, is undefined) is refused
    like a singular H: one line naming the file and line, or skipped and listed with --skip-bad."""
    source = shared_data / "scannet_sample"
    root = tmp_path / "scannet"
    shutil.copytree(source, root)
    lines = (root / "pairs_with_gt.txt").read_text().splitlines()
    fields = lines[1].split()
    fields[-16:] = [str(v) for v in np.eye(4).ravel()]
    lines[1] = " ".join(fields)
    (root / "pairs_with_gt.txt").write_text("\n".join(lines) + "\n")
    line = one_line_error(invoke("yfcc", "--root", root, "--pairs", root / "pairs_with_gt.txt", "--out", tmp_path / "r",
                                 "--matcher", "sift"))
    assert "pairs_with_gt.txt:2" in line and "has no translation" in line
    result = invoke("yfcc", "--root", root, "--pairs", root / "pairs_with_gt.txt", "--out", tmp_path / "r", "--matcher", "sift",
                    "--skip-bad", "--limit", 1, "--max-side", 320)
    assert result.exit_code == 0
    assert "has no translation" in pd.read_csv(tmp_path / "r" / "skipped.csv")["reason"].iloc[0]


def test_negative_viz_is_refused(shared_data, tmp_path):
    line = one_line_error(invoke("hpatches", "--root", shared_data / "hpatches-sequences-release", "--out", tmp_path / "v",
                                 "--matcher", "sift", "--viz", -1))
    assert "--viz must be a whole number, at least 0, got -1" in line


def huge_png(path: Path, side: int = 20000) -> Path:
    """A valid grey PNG of side x side zeros: a few hundred KB on disk."""
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    rows = zlib.compress(b"".join(b"\x00" * (side + 1) for _ in range(side)), 9)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, 0))
                     + chunk(b"IDAT", rows) + chunk(b"IEND", b""))
    return path


def test_an_image_over_the_pixel_bound_is_refused_from_its_header(tmp_path, shared_data):
    big = huge_png(tmp_path / "big.png")
    assert big.stat().st_size < 1 << 20
    small = shared_data / "hpatches-sequences-release" / "v_boat" / "1.ppm"
    result, peak = cli_peak("match", big, small, "--matcher", "sift", "--out", tmp_path / "m")
    assert peak < 1.5 * 2**30, peak / 2**30  # decoded, the image alone would take 1.1 GiB, in RGB
    lines = error_lines(result)
    assert result.returncode == 2 and len(lines) == 1, result.stderr[-2000:]
    assert f"{big}: 20000 x 20000 (400 megapixels), over the bound of 100 megapixels" in lines[0]
    assert "--max-side" in lines[0] and "E3CM_BENCH_MAX_PIXELS" in lines[0]
    # the setting raises the bound: then the image is decoded (a 2 MP bound still refuses it)
    raised = cli("match", big, small, "--matcher", "sift", "--out", tmp_path / "m", timeout=120,
                 env={**os.environ, "E3CM_BENCH_MAX_PIXELS": "2000000"})
    assert "over the bound of 2 megapixels" in raised.stderr


# --------------------------------------------------------------------------- 6. one line, not a traceback


def test_out_naming_a_file_or_unwritable_is_one_line(shared_data, tmp_path):
    image = shared_data / "hpatches-sequences-release" / "v_boat" / "1.ppm"
    afile = tmp_path / "afile"
    afile.write_text("x")
    for args in (["match", image, image, "--matcher", "sift", "--out", afile],
                 ["hpatches", "--root", shared_data / "hpatches-sequences-release", "--out", afile / "run", "--matcher", "sift"]):
        line = one_line_error(invoke(*args))
        assert f"{afile}: is a file, not a folder" in line
    readonly = tmp_path / "ro"
    readonly.mkdir()
    if os.geteuid() == 0:  # root writes through file modes: a read-only mount says it
        mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=64k", "tmpfs", str(readonly)], capture_output=True)
        if mounted.returncode != 0:
            pytest.skip("cannot mount a read-only tmpfs here")
    else:
        readonly.chmod(0o555)
    try:
        for out in (readonly, readonly / "new"):
            line = one_line_error(invoke("match", image, image, "--matcher", "sift", "--out", out))
            assert str(out) in line and ("not writable" in line or "cannot create" in line), line
    finally:
        if os.geteuid() == 0:
            subprocess.run(["umount", "-l", str(readonly)], capture_output=True)
        else:
            readonly.chmod(0o755)


def test_match_on_a_pair_too_large_for_memory_is_one_line(shared_data, tmp_path, monkeypatch):
    import e3cm_bench.matchers.deep as deep

    monkeypatch.setattr(deep, "available_memory", lambda device: 64 << 20)
    image = shared_data / "hpatches-sequences-release" / "v_boat" / "1.ppm"
    line = one_line_error(invoke("match", image, image, "--backbone", "efficientnet_lite0", "--out", tmp_path / "m"))
    assert "out of memory: about" in line and "GiB needed at" in line and "--max-side" in line


def test_a_full_disk_while_the_reports_are_written_is_one_line_and_keeps_the_matches(shared_data, tmp_path, monkeypatch):
    import e3cm_bench.pipeline.evaluate as evaluate

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "run" / "mma.png"))

    monkeypatch.setattr(evaluate, "write_reports", full)
    line = one_line_error(invoke("hpatches", "--root", shared_data / "hpatches-sequences-release", "--out", tmp_path / "run",
                                 "--matcher", "sift", "--sequences", "v_boat", "--limit", 2))
    assert f"{tmp_path / 'run' / 'mma.png'}: no space left on device" in line and "every pair already written resumes" in line
    assert len(MatchCache(tmp_path / "run" / "matches.h5").names()) == 2
