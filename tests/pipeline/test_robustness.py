"""A run under bad data and signals: nothing lost, nothing mixed, no traceback, no code run from data.

Each test corrupts its own copy of ../shared/data. Real subprocesses and real signals where
the behaviour depends on them (the lock, SIGKILL, SIGINT, memory limits).
"""

from __future__ import annotations

import os
import pickle
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

import e3cm_bench.storage.cache as cache_module
from e3cm_bench.benchmarks import EvalSettings
from e3cm_bench.storage.cache import MatchCache
from e3cm_bench.method.spec import MethodSpec
from e3cm_bench.pipeline.runner import run_benchmark
from helpers import flat, invoke, one_line_error, same_csvs

LITE = ["--backbone", "efficientnet_lite0"]


def _default_sigint() -> None:
    # A shell starts background jobs with SIGINT ignored, and Python then installs no
    # KeyboardInterrupt handler; the command must see Ctrl-C as a user's terminal sends it.
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def cli(*args, **kwargs) -> subprocess.Popen:
    """The real command in its own process (SIGINT as in a terminal, whatever runs the tests)."""
    return subprocess.Popen([sys.executable, "-m", "e3cm_bench.cli", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, preexec_fn=_default_sigint, **kwargs)


# The real command, but once its N-th pair is stored (its block file written and closed, as
# after any pair) it writes the stored names to MARKER (atomically) and waits there, in the
# main thread, where Python runs signal handlers, until a signal ends it. A test then signals
# it at a known point, however fast or slow the machine is. The wait is a loop of short
# sleeps, not signal.pause(): a signal that lands between the marker and the wait would be
# missed by pause() for good, while the loop sees it at its next turn.
_PARK_AFTER_PAIRS = """
import os, sys, threading, time
from pathlib import Path
from e3cm_bench.storage.cache import MatchCache

after, marker = int(sys.argv.pop(1)), Path(sys.argv.pop(1))
store, stored = MatchCache.write, []

def store_then_park(self, name, matches, attrs=None):
    store(self, name, matches, attrs)
    stored.append(name)
    if len(stored) < after:
        return
    if threading.current_thread() is not threading.main_thread():  # a signal would not reach the wait
        sys.stderr.write(f"parked run: pairs are stored in thread {threading.current_thread().name!r}, "
                         "not the main one; the test's way of stopping the run must change\\n")
        sys.stderr.flush()
        os._exit(3)
    Path(f"{marker}.tmp").write_text("\\n".join(stored))
    os.replace(f"{marker}.tmp", marker)
    while True:
        time.sleep(0.05)

MatchCache.write = store_then_park
from e3cm_bench.cli import app
app()
"""


def parked_cli(after_pairs: int, marker: Path, *args) -> subprocess.Popen:
    """cli(*args) that stops for a signal once it has stored `after_pairs` pairs (see _PARK_AFTER_PAIRS)."""
    return subprocess.Popen([sys.executable, "-c", _PARK_AFTER_PAIRS, str(after_pairs), str(marker), *map(str, args)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=_default_sigint)


def wait_parked(process: subprocess.Popen, marker: Path, timeout: float = 600) -> list[str]:
    """The names a parked_cli run had stored when it stopped; fails the test if it ends or takes
    longer than `timeout` seconds (a deadline for a stuck run only: the verdict never depends on it)."""
    deadline = time.monotonic() + timeout
    while not marker.exists():
        if process.poll() is not None:
            out, err = process.communicate()
            pytest.fail(f"the run ended (code {process.returncode}) before storing the pairs it was to stop after:\n"
                        f"{out[-2000:]}\n{err[-4000:]}")
        if time.monotonic() > deadline:
            process.kill()
            out, err = process.communicate()
            pytest.fail(f"the run had not stored the pairs it was to stop after within {timeout:.0f} s:\n"
                        f"{out[-2000:]}\n{err[-4000:]}")
        time.sleep(0.02)  # polls a run that waits for us: how long this takes changes nothing
    return marker.read_text().split("\n")


@pytest.fixture
def hpatches_copy(shared_data, tmp_path) -> Path:
    root = tmp_path / "hpatches"
    shutil.copytree(shared_data / "hpatches-sequences-release", root)
    return root


@pytest.fixture
def scannet_copy(shared_data, tmp_path) -> Path:
    root = tmp_path / "scannet"
    shutil.copytree(shared_data / "scannet_sample", root)
    return root


# ----------------------------------------------------------------------------- 1. the lock


@pytest.mark.slow  # 404 s (the quick check: tests/cli/test_cli_messages.py) alone on a loaded 2-core machine (docs/development.md, Testing)
def test_a_second_run_into_the_same_folder_is_refused_while_the_first_runs(hpatches_copy, tmp_path):
    out = tmp_path / "run"
    # The first run holds the lock, stopped after its first pair until it is sent Ctrl-C, so it
    # is still running while the second is refused, however fast the machine.
    first = parked_cli(1, tmp_path / "parked", "hpatches", "--root", hpatches_copy, "--out", out, *LITE,
                       "--max-side", 320)
    assert len(wait_parked(first, tmp_path / "parked")) == 1
    second = cli("hpatches", "--root", hpatches_copy, "--out", out, "--matcher", "sift")
    _, err = second.communicate(timeout=120)
    still_running = first.poll() is None
    first.send_signal(signal.SIGINT)
    _, first_err = first.communicate(timeout=120)
    assert still_running, "the first run ended before the second was refused: the test proves nothing"
    assert first.returncode == 130, first_err
    assert second.returncode == 2, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "another run is using this folder" in lines[0] and f"pid {first.pid}" in lines[0]
    assert "Traceback" not in err
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["identity"]["matcher"] == "e3cm"  # the second run wrote nothing
    # Released when the first run ended (here by Ctrl-C): the next run gets past the lock to
    # the settings check, which refuses to mix matchers.
    line = one_line_error(invoke("hpatches", "--root", hpatches_copy, "--out", out, "--matcher", "sift"))
    assert "other settings" in line and "another run" not in line


# ----------------------------------------------------------------------------- 2. identity


@pytest.mark.slow  # 226 s alone on a loaded 2-core machine (docs/development.md, Testing)
def test_another_seed_of_a_random_matcher_is_another_set_of_matches(hpatches_copy, tmp_path):
    out = tmp_path / "run"
    common = ["hpatches", "--root", hpatches_copy, "--out", out, "--matcher", "dfm", *LITE, "--max-side", 200, "--limit", 1]
    assert invoke(*common, "--seed", 0).exit_code == 0
    line = one_line_error(invoke(*common, "--seed", 1))
    assert "seed" in line and "--overwrite" in line
    # top8 draws no random number: its matches are reused under another evaluation seed.
    out2 = tmp_path / "top8"
    top8 = ["hpatches", "--root", hpatches_copy, "--out", out2, *LITE, "--max-side", 200, "--limit", 1]
    assert invoke(*top8, "--seed", 0).exit_code == 0
    again = invoke(*top8, "--seed", 1)
    assert again.exit_code == 0 and "all 1 pairs found" in flat(again.output)
    assert yaml.safe_load((out2 / "config.yaml").read_text())["evaluation"]["seed"] == 1


def test_precision_thresholds_reach_the_metrics(shared_data, tmp_path):
    root = shared_data / "megadepth_test_1500"
    options = {"scene_info": [root / "scene_info" / "kitti00_seq.npz"]}
    ev = EvalSettings(precision_thresholds=(1e-3, 1e-5))
    summary = run_benchmark("megadepth", tmp_path / "run", MethodSpec.create("sift", max_side=640), root=root,
                            dataset_options=options, ev=ev, limit=2)
    per_pair = pd.read_csv(tmp_path / "run" / "per_pair.csv")
    assert [c for c in per_pair.columns if c.startswith("precision")] == ["precision@1e-3", "precision@1e-5"]
    assert summary["precision@1e-3"].item() > summary["precision@1e-5"].item()


# ----------------------------------------------------------------------------- 3. bad ground truth


@pytest.mark.slow  # 50 s alone on a loaded 2-core machine (docs/development.md, Testing)
def test_singular_or_non_finite_homography_is_an_error_or_a_counted_skip(hpatches_copy, tmp_path):
    np.savetxt(hpatches_copy / "v_boat" / "H_1_4", np.zeros((3, 3)))
    args = ["hpatches", "--root", hpatches_copy, "--matcher", "sift", "--max-side", 320]
    line = one_line_error(invoke(*args, "--out", tmp_path / "a"))
    assert "v_boat/H_1_4" in line and "singular" in line and "--skip-bad" in line
    assert not (tmp_path / "a").exists()  # refused before anything was written
    result = invoke(*args, "--out", tmp_path / "b", "--skip-bad")
    assert result.exit_code == 0 and "1 of 15 skipped" in flat(result.output)
    skipped = pd.read_csv(tmp_path / "b" / "skipped.csv")
    assert list(skipped["pair"]) == ["v_boat/1-4"] and "singular" in skipped["reason"][0]
    summary = pd.read_csv(tmp_path / "b" / "summary.csv")
    assert summary["n_pairs"].item() == 14 and summary["n_skipped"].item() == 1
    (hpatches_copy / "v_boat" / "H_1_4").write_text("1 0 0\n0 nan 0\n0 0 1\n")
    line = one_line_error(invoke(*args, "--out", tmp_path / "c"))
    assert "non-finite" in line and "shape" not in line


def test_all_zero_intrinsics_name_the_file_and_line(scannet_copy, tmp_path):
    pairs = scannet_copy / "pairs_with_gt.txt"
    lines = pairs.read_text().splitlines()
    fields = lines[2].split()
    fields[4:13] = ["0"] * 9  # K0 of line 3
    lines[2] = " ".join(fields)
    pairs.write_text("\n".join(lines) + "\n")
    args = ["yfcc", "--root", scannet_copy, "--pairs", pairs, "--matcher", "sift", "--max-side", 320]
    line = one_line_error(invoke(*args, "--out", tmp_path / "a"))
    assert f"{pairs}:3: K0" in line and "focal" in line
    result = invoke(*args, "--out", tmp_path / "b", "--skip-bad", "--limit", 1)
    assert result.exit_code == 0 and "1 of 8 skipped" in flat(result.output)


# ----------------------------------------------------------------------------- 4. no code from data


class _CreatesAFile:
    def __init__(self, path: str):
        self.path = path

    def __reduce__(self):
        return (os.system, (f"touch {self.path}",))


def test_a_crafted_scene_info_pickle_runs_no_code(shared_data, tmp_path):
    marker = tmp_path / "pwned"
    crafted = tmp_path / "scene_info.npz"
    crafted.write_bytes(pickle.dumps({"image_paths": _CreatesAFile(str(marker))}))
    line = one_line_error(invoke("megadepth", "--root", shared_data / "megadepth_test_1500", "--scene-info", crafted,
                                 "--out", tmp_path / "run", "--matcher", "sift"))
    assert str(crafted) in line and "posix.system" in line or "os.system" in line
    assert not marker.exists()


# ----------------------------------------------------------------------------- 5. damaged cache


def test_a_damaged_cache_file_costs_only_its_pairs(hpatches_copy, tmp_path, monkeypatch):
    monkeypatch.setattr(cache_module, "BLOCK_PAIRS", 2)  # 6 pairs -> 3 files
    args = ["hpatches", "--root", hpatches_copy, "--matcher", "sift", "--max-side", 320, "--limit", 6]
    reference, out = tmp_path / "reference", tmp_path / "run"
    assert invoke(*args, "--out", reference).exit_code == 0
    assert invoke(*args, "--out", out).exit_code == 0
    blocks = MatchCache(out / "matches.h5").blocks()
    assert len(blocks) == 3
    blocks[1].write_bytes(blocks[1].read_bytes()[:-2048])  # 2 KiB cut off the middle file
    result = invoke(*args, "--out", out)
    text = flat(result.output)
    # of the cut file's two pairs, the one whose data lay before the cut is read back
    assert result.exit_code == 0 and "is damaged" in text and "6 pairs, 5 already in" in text
    same_csvs(out, reference)


# ----------------------------------------------------------------------------- 6. one bad input


def test_a_truncated_image_is_found_before_matching_or_skipped(hpatches_copy, tmp_path):
    image = hpatches_copy / "v_graffiti" / "3.ppm"
    image.write_bytes(image.read_bytes()[:50_000])
    args = ["hpatches", "--root", hpatches_copy, "--matcher", "sift", "--max-side", 320]
    result = invoke(*args, "--out", tmp_path / "a")
    line = one_line_error(result)
    assert "v_graffiti/3.ppm" in line and "cut short" in line
    assert not (tmp_path / "a").exists()  # found before any matching
    result = invoke(*args, "--out", tmp_path / "b", "--skip-bad")
    assert result.exit_code == 0 and "Premature" not in result.output
    assert list(pd.read_csv(tmp_path / "b" / "skipped.csv")["pair"]) == ["v_graffiti/1-3"]


def test_missing_homography_and_empty_sequence_are_skipped(hpatches_copy, tmp_path):
    (hpatches_copy / "v_boat" / "H_1_2").unlink()
    for f in (hpatches_copy / "i_leuven").iterdir():
        f.unlink()
    result = invoke("hpatches", "--root", hpatches_copy, "--matcher", "sift", "--max-side", 320,
                    "--out", tmp_path / "run", "--skip-bad")
    assert result.exit_code == 0 and "6 of 15 skipped" in flat(result.output)
    skipped = pd.read_csv(tmp_path / "run" / "skipped.csv")
    assert set(skipped["pair"]) == {"v_boat/1-2", *(f"i_leuven/1-{k}" for k in range(2, 7))}
    assert pd.read_csv(tmp_path / "run" / "summary.csv")["n_pairs"].item() == 9


def test_an_image_that_fails_to_decode_mid_run_keeps_the_pairs_before_it(hpatches_copy, tmp_path, monkeypatch):
    import e3cm_bench.ground.images as images_module

    real = images_module.image_file_problem
    bad = hpatches_copy / "v_boat" / "4.ppm"
    # A PNG magic and an IEND at the end, garbage between: whole by the cheap check, not decodable.
    bad.write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 20 + b"IEND\xaeB`\x82")
    monkeypatch.setattr(images_module, "image_file_problem", lambda p: None if Path(p) == bad else real(p))
    args = ["hpatches", "--root", hpatches_copy, "--matcher", "sift", "--max-side", 320, "--sequences", "v_boat"]
    result = invoke(*args, "--out", tmp_path / "a")
    assert result.exit_code == 2 and "v_boat/1-4" in result.stderr and "kept" in result.stderr
    assert MatchCache(tmp_path / "a" / "matches.h5").names() == ["v_boat/1-2", "v_boat/1-3"]
    # With --skip-bad the run goes on past it, and says so.
    result = invoke(*args, "--out", tmp_path / "b", "--skip-bad")
    assert result.exit_code == 0 and "1 pair(s) skipped" in flat(result.output)
    assert list(pd.read_csv(tmp_path / "b" / "skipped.csv")["pair"]) == ["v_boat/1-4"]
    assert pd.read_csv(tmp_path / "b" / "summary.csv")["n_pairs"].item() == 4


# ----------------------------------------------------------------------------- 7-8. options


def test_a_rejected_option_writes_nothing(hpatches_copy, tmp_path):
    out = tmp_path / "run"
    args = ["hpatches", "--root", hpatches_copy, "--out", out, "--matcher", "sift", "--limit", 1]
    line = one_line_error(invoke(*args, "--max-side", -5))
    assert "--max-side" in line and not out.exists()
    assert invoke(*args, "--max-side", 320).exit_code == 0  # the corrected command is not refused


@pytest.mark.parametrize("option, value, words", [
    ("--limit", 0, "--limit must be a whole number, at least 1"), ("--limit", -2, "--limit must be a whole number, at least 1"),
    ("--ratio", "0.9,1.5,0.9,0.9,0.9", "--ratio values must be in (0, 1]"),
])
def test_silently_wrong_options_are_refused(hpatches_copy, tmp_path, option, value, words):
    line = one_line_error(invoke("hpatches", "--root", hpatches_copy, "--out", tmp_path / "o", *LITE, option, value))
    assert words in line and not (tmp_path / "o").exists()


def test_experiment_configs_are_checked_whole_before_any_run(hpatches_copy, tmp_path):
    config = tmp_path / "exp.yaml"
    config.write_text(yaml.safe_dump({"benchmark": "hpatches", "datset": {}, "methods": [{"matcher": "sift"}]}))
    line = one_line_error(invoke("reproduce", config, "--root", hpatches_copy, "--out", tmp_path / "o"))
    assert str(config) in line and "datset" in line
    config.write_text(yaml.safe_dump({"benchmark": "hpatches", "methods": [
        {"matcher": "sift"}, {"matcher": "e3cm", "estimator": "ransca"}]}))
    line = one_line_error(invoke("reproduce", config, "--root", hpatches_copy, "--out", tmp_path / "o"))
    assert str(config) in line and "methods[1]" in line and "ransca" in line
    assert not (tmp_path / "o").exists()  # the sift method before it did not run


# ----------------------------------------------------------------------------- 9. tracebacks


@pytest.mark.slow  # 22 s alone on a loaded 2-core machine (docs/development.md, Testing)
def test_an_image_too_large_for_memory_is_one_line(tmp_path):
    """A real allocation failure: the process may grow by 3 GiB, the image needs more at full size."""
    big = tmp_path / "big"
    (big / "v_big").mkdir(parents=True)
    rng = np.random.default_rng(0)
    import cv2

    image = rng.integers(0, 256, (2000, 3000, 3), dtype=np.uint8)
    for k in range(1, 3):
        cv2.imwrite(str(big / "v_big" / f"{k}.ppm"), image)
    np.savetxt(big / "v_big" / "H_1_2", np.eye(3))
    for k in range(3, 7):
        cv2.imwrite(str(big / "v_big" / f"{k}.ppm"), image[:8, :8])
        np.savetxt(big / "v_big" / f"H_1_{k}", np.eye(3))
    # The CUDA build of torch maps gigabytes of address space when imported: limit what comes after.
    code = ("import resource, torch, torchvision, cv2\n"
            "size = int(next(l for l in open('/proc/self/status') if l.startswith('VmSize')).split()[1]) << 10\n"
            "resource.setrlimit(resource.RLIMIT_AS, (size + (3 << 30), size + (3 << 30)))\n"
            "from e3cm_bench.cli import app; app()")
    done = subprocess.run([sys.executable, "-c", code, "hpatches", "--root", str(big), "--out", str(tmp_path / "o"),
                           *LITE, "--max-side", "0", "--limit", "1"], capture_output=True, text=True, timeout=300)
    print(done.stdout[-2000:], done.stderr[-2000:])
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == 2 and len(lines) == 1
    assert "do not fit in memory" in lines[0] and "--max-side" in lines[0] and "Traceback" not in done.stderr


# ----------------------------------------------------------------------------- 10. small things


def test_reports_are_created_with_the_usual_file_mode(hpatches_copy, tmp_path):
    old = os.umask(0o022)
    try:
        assert invoke("hpatches", "--root", hpatches_copy, "--out", tmp_path / "r", "--matcher", "sift",
                      "--limit", 1, "--max-side", 320).exit_code == 0
    finally:
        os.umask(old)
    for name in ("per_pair.csv", "summary.csv", "mma.png", "config.yaml"):
        assert (tmp_path / "r" / name).stat().st_mode & 0o777 == 0o644, name


def test_console_table_keeps_bracketed_labels(hpatches_copy, tmp_path):
    run = tmp_path / "r"
    assert invoke("hpatches", "--root", hpatches_copy, "--out", run, "--matcher", "sift", "--limit", 1,
                  "--max-side", 320, "--label", "sift [custom]").exit_code == 0
    result = invoke("table", run, "--out", tmp_path / "t", "--no-compare")
    assert "sift [custom]" in result.output


# ----------------------------------------------------------------------------- 11. interruption


@pytest.fixture(scope="module")
def interrupt_args(shared_data, tmp_path_factory):
    root = tmp_path_factory.mktemp("intr") / "hpatches"
    shutil.copytree(shared_data / "hpatches-sequences-release", root)
    # Feature reuse off: every pair runs the backbone itself, so the resume is tested apart from
    # the feature cache. (It also once kept the run slow enough for a signal to land mid-run;
    # the interrupted runs now stop at a known pair instead, see parked_cli.)
    args = ["hpatches", "--root", root, "--matcher", "direct", *LITE, "--max-side", 320, "--feature-cache-mb", 0]
    reference = root.parent / "reference"
    done = subprocess.run([sys.executable, "-m", "e3cm_bench.cli", *map(str, args), "--out", str(reference)],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    return args, reference


@pytest.mark.slow  # 81-109 s each, 74 s for its first run alone on a loaded 2-core machine (docs/development.md, Testing)
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGINT])
def test_a_signalled_run_resumes_to_the_same_csvs(interrupt_args, tmp_path, sig):
    args, reference = interrupt_args
    out, marker = tmp_path / "run", tmp_path / "parked"
    process = parked_cli(2, marker, *args, "--out", out)
    stored = wait_parked(process, marker)  # the run waits, after its 2nd pair, for the signal
    process.send_signal(sig)
    _, err = process.communicate(timeout=120)
    assert process.returncode == (-9 if sig == signal.SIGKILL else 130), err
    if sig == signal.SIGINT:
        assert "interrupted" in err and "Traceback" not in err
    assert len(stored) == 2 and MatchCache(out / "matches.h5").names() == sorted(stored)  # 13 of 15 left
    rerun = subprocess.run([sys.executable, "-m", "e3cm_bench.cli", *map(str, args), "--out", str(out)],
                           capture_output=True, text=True, timeout=600)
    assert rerun.returncode == 0, rerun.stderr
    same_csvs(out, reference)


@pytest.mark.slow  # 31 s alone on a loaded 2-core machine (docs/development.md, Testing)
def test_two_runs_with_the_same_seed_give_identical_csvs(interrupt_args, tmp_path):
    args, reference = interrupt_args
    again = subprocess.run([sys.executable, "-m", "e3cm_bench.cli", *map(str, args), "--out", str(tmp_path / "again")],
                           capture_output=True, text=True, timeout=600)
    assert again.returncode == 0
    same_csvs(tmp_path / "again", reference)


@pytest.mark.slow  # 14 s in the fast set under a load of about 7 on the shared 2-core machine (docs/development.md, Testing)
def test_an_undecodable_image_ahead_of_a_batch_is_met_at_its_own_pair(hpatches_copy, tmp_path, monkeypatch):
    """--backbone-batch decodes the coming pairs to batch their images: a pair whose image
    cannot be decoded is left out of the batch, and its error (or, with --skip-bad, its
    skipping) comes at its own pair, as without batching."""
    import e3cm_bench.ground.images as images_module

    real = images_module.image_file_problem
    bad = hpatches_copy / "v_boat" / "4.ppm"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 20 + b"IEND\xaeB`\x82")
    monkeypatch.setattr(images_module, "image_file_problem", lambda p: None if Path(p) == bad else real(p))
    args = ["hpatches", "--root", hpatches_copy, "--matcher", "direct", "--backbone", "efficientnet_lite0",
            "--max-side", 160, "--sequences", "v_boat", "--backbone-batch", 4]
    result = invoke(*args, "--out", tmp_path / "a")
    assert result.exit_code == 2 and "v_boat/1-4" in result.stderr and "kept" in result.stderr
    result = invoke(*args, "--out", tmp_path / "b", "--skip-bad")
    assert result.exit_code == 0 and "1 pair(s) skipped" in flat(result.output)
    assert list(pd.read_csv(tmp_path / "b" / "skipped.csv")["pair"]) == ["v_boat/1-4"]
    assert pd.read_csv(tmp_path / "b" / "summary.csv")["n_pairs"].item() == 4
    reuse = yaml.safe_load((tmp_path / "b" / "config.yaml").read_text())["feature_reuse"]
    assert reuse["largest_batch"] == 4 and reuse["backbone_passes"] == reuse["distinct_images"] == 5
