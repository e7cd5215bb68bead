"""Hostile inputs: plugins that exit or hang, garbage that
looked like results, tracebacks turned into one line, and files that declare more than they hold."""

from __future__ import annotations

import importlib
import os
import shutil
import subprocess
import sys
import textwrap
import time
import zipfile
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import pytest
import yaml

from e3cm_bench.storage.cache import MAX_PAIR_MATCHES, MatchCache
from e3cm_bench.datasets import megadepth
from e3cm_bench.datasets.megadepth import load_scene_info
from e3cm_bench.matchers import MatcherEntry, register, registry, unregister
from e3cm_bench.matchers.guards import PairTimeout, PluginExit, describe_matcher, no_exit, pair_time_limit
from e3cm_bench.ground.matches import Matches, distinct
from helpers import flat, invoke, one_line_error

@pytest.fixture(scope="module")
def boat(shared_data, tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("data") / "hpatches"
    shutil.copytree(shared_data / "hpatches-sequences-release" / "v_boat", root / "v_boat")
    return root


SIFT = ("--matcher", "sift", "--max-side", 320)


@pytest.fixture(scope="module")
def made_run(boat, tmp_path_factory) -> Path:
    """A SIFT run over the five pairs of v_boat."""
    out = tmp_path_factory.mktemp("made") / "sift"
    assert invoke("hpatches", "--root", boat, "--out", out, *SIFT).exit_code == 0
    return out


def run_copy(made_run: Path, folder: Path) -> Path:
    shutil.copytree(made_run, folder)
    return folder


# ----------------------------------------------------------------------------- 9. plugins


def plugin_site(tmp_path: Path, monkeypatch, name: str, code: str) -> Path:
    """An installed distribution whose entry point `name` is the module plug_<name> holding `code`."""
    site = tmp_path / f"site_{name}"
    info = site / f"plug_{name}-1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: plug-{name}\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(f"[e3cm_bench.matchers]\n{name} = plug_{name}:ENTRY\n")
    (site / f"plug_{name}.py").write_text(textwrap.dedent(code))
    monkeypatch.syspath_prepend(str(site))
    importlib.invalidate_caches()
    monkeypatch.setattr(registry, "_plugins_loaded", False)  # as in a fresh process
    return site


def test_a_plugin_exiting_at_import_touches_neither_sift_nor_the_listing(boat, tmp_path, monkeypatch):
    marker = tmp_path / "imported"
    plugin_site(tmp_path, monkeypatch, "exits", f"""
        import sys
        open({str(marker)!r}, "w").close()
        sys.exit(7)
    """)
    try:
        result = invoke("hpatches", "--root", boat, "--out", tmp_path / "run", "--limit", 1, *SIFT)
        assert result.exit_code == 0, result.output
        assert not marker.exists()  # a built-in asked for: no plugin imported at all
        listing = invoke("matchers")
        assert listing.exit_code == 0 and "sift  (built-in)" in listing.output
        assert "exits (not loaded) plugin plug_exits:ENTRY (plug-exits 1.0) failed to load: called sys.exit(7)" \
            in flat(listing.output)
        assert marker.exists()
        line = one_line_error(invoke("hpatches", "--root", boat, "--out", tmp_path / "x", "--matcher", "exits"))
        assert "plug-exits 1.0" in line and "called sys.exit(7)" in line
    finally:
        registry._BROKEN.pop("exits", None)


def test_a_plugin_hanging_at_import_is_given_up_on_in_time(tmp_path, monkeypatch):
    plugin_site(tmp_path, monkeypatch, "sleeps", """
        import time
        time.sleep(120)
    """)
    monkeypatch.setenv("E3CM_BENCH_PLUGIN_TIMEOUT", "1")
    try:
        started = time.monotonic()
        listing = invoke("matchers")
        assert time.monotonic() - started < 30
        assert listing.exit_code == 0 and "sift  (built-in)" in listing.output
        assert "sleeps (not loaded) plugin plug_sleeps:ENTRY (plug-sleeps 1.0) failed to load: did not finish " \
               "importing within 1 s" in flat(listing.output)
    finally:
        registry._BROKEN.pop("sleeps", None)


def test_a_factory_calling_sys_exit_is_that_matchers_failure(boat, tmp_path, monkeypatch):
    (tmp_path / "mods").mkdir()
    (tmp_path / "mods" / "exiting_factory.py").write_text("import sys\n\ndef build():\n    sys.exit(5)\n")
    monkeypatch.syspath_prepend(str(tmp_path / "mods"))
    register(MatcherEntry("exits-when-built", "exits in build", build=lambda settings: sys.exit(5), origin="test"))
    try:
        line = one_line_error(invoke("hpatches", "--root", boat, "--out", tmp_path / "a", "--matcher",
                                     "exiting_factory:build"))
        assert line.endswith("--matcher exiting_factory:build: build() called sys.exit(5)")
        line = one_line_error(invoke("hpatches", "--root", boat, "--out", tmp_path / "b", "--matcher", "exits-when-built"))
        assert "matcher exits-when-built (test): building it called sys.exit(5)" in line
    finally:
        unregister("exits-when-built")
        sys.modules.pop("exiting_factory", None)


class Exits:
    """Sound matches for the first pair, then sys.exit(0) (or a config() that cannot be written)."""

    keypoints_in_image = True

    def __init__(self, config=None):
        self.calls, self.name, self._config = 0, "exits-in-match", config

    def match(self, image0, image1):
        self.calls += 1
        if self.calls > 1:
            sys.exit(0)
        k = np.array([[10.0, 10.0], [20.0, 30.0], [40.0, 15.0], [25.0, 25.0]])
        return Matches(k, k + 1, np.ones(4))

    def config(self):
        if self._config == "raises":
            raise RuntimeError("no config today")
        return {"matcher": self.name, **({"model": object()} if self._config == "object" else {})}


def test_sys_exit_inside_match_fails_the_pair_in_one_line(boat, tmp_path):
    register(MatcherEntry("exits-in-match", "exits on its second pair", build=lambda s: Exits(), origin="test"))
    try:
        out = tmp_path / "run"
        line = one_line_error(invoke("hpatches", "--root", boat, "--out", out, "--matcher", "exits-in-match"))
        assert line.startswith("error: pair v_boat/1-3: matcher exits-in-match") and "sys.exit(0)" in line
        assert MatchCache(out / "matches.h5").names() == ["v_boat/1-2"]
    finally:
        unregister("exits-in-match")


@pytest.mark.parametrize("kind, says", [("raises", "config() raised RuntimeError: no config today"),
                                        ("object", "config() returned a value YAML cannot write")])
def test_a_config_that_cannot_be_written_is_one_line(boat, tmp_path, kind, says):
    register(MatcherEntry("exits-in-match", "bad config", build=lambda s: Exits(kind), origin="test"))
    try:
        line = one_line_error(invoke("hpatches", "--root", boat, "--out", tmp_path / "run", "--matcher",
                                     "exits-in-match", "--limit", 1))
        assert f"matcher exits-in-match: {says}" in line
    finally:
        unregister("exits-in-match")


def test_the_guards_turn_exits_bad_configs_and_slow_pairs_into_errors():
    with pytest.raises(PluginExit, match=r"sys\.exit\(3\) called inside match\(\)"):
        with no_exit("match()"):
            sys.exit(3)
    with pytest.raises(ValueError, match="matcher exits-in-match: config\\(\\) raised RuntimeError: no config today"):
        describe_matcher(Exits("raises"))
    with pytest.raises(ValueError, match="config\\(\\) returned a value YAML cannot write"):
        describe_matcher(Exits("object"))
    assert describe_matcher(Exits()) == {"matcher": "exits-in-match"}
    started = time.monotonic()
    with pytest.raises(PairTimeout, match="matcher slow, pair a/1-2: no result within --pair-timeout 0.2 s"):
        with pair_time_limit(0.2, "matcher slow, pair a/1-2"):
            while True:
                time.sleep(0.01)
    assert time.monotonic() - started < 5
    with pair_time_limit(5, "matcher quick, pair a/1-2"):
        pass
    time.sleep(0.05)  # the alarm was cancelled: nothing fires after the block


# ----------------------------------------------------------------------------- 10. garbage


class Repeats:
    """One correct match of v_boat 1-k (the identity is wrong, so: a point and its true image), 5000 times."""

    keypoints_in_image = True
    name = "repeats"

    def match(self, image0, image1):
        k = np.tile([[100.0, 100.0]], (5000, 1))
        return Matches(k, k, np.ones(5000))


def test_distinct_keeps_each_correspondence_once_and_counts_the_rest():
    k = np.array([[1.0, 2.0], [3.0, 4.0], [1.0, 2.0], [5.0, 6.0]])
    kept, dropped = distinct(Matches(k, k + 1, np.arange(4)))
    assert dropped == 1 and kept.keypoints0.tolist() == [[1, 2], [3, 4], [5, 6]] and kept.scores.tolist() == [0, 1, 3]
    same0 = Matches(k[[0, 0]], np.array([[1.0, 1.0], [2.0, 2.0]]), None)  # one point, two partners: not a repeat
    assert distinct(same0)[1] == 0


def test_one_match_repeated_5000_times_counts_once(boat, tmp_path):
    register(MatcherEntry("repeats", "one match, 5000 times", build=lambda s: Repeats(), origin="test"))
    try:
        out = tmp_path / "run"
        result = invoke("hpatches", "--root", boat, "--out", out, "--matcher", "repeats", "--limit", 1, "--viz", 1)
        assert result.exit_code == 0, result.output
        row = pd.read_csv(out / "per_pair.csv").iloc[0]
        assert row["n_matches"] == 1 and row["n_duplicates"] == 4999
        assert not np.isfinite(row["h_error"])  # one correspondence: no homography, a failed pair
        assert pd.read_csv(out / "summary.csv").iloc[0]["n_matches"] == 1
        assert "4999 repeated correspondence(s) in 1 pair(s) counted once" in flat(result.output)
        assert len(MatchCache(out / "matches.h5").read(row["pair"])) == 5000  # the cache keeps what the matcher said
    finally:
        unregister("repeats")


def test_each_pair_row_counts_what_the_cache_holds_beyond_its_distinct_matches(made_run):
    """SIFT returns a keypoint once per orientation: its rows must add up to the cached matches."""
    per_pair = pd.read_csv(made_run / "per_pair.csv")
    columns = list(per_pair.columns)
    assert columns.index("n_duplicates") == columns.index("n_matches") + 1
    cache = MatchCache(made_run / "matches.h5")
    for row in per_pair.itertuples():
        assert row.n_matches + row.n_duplicates == len(cache.read(row.pair))


@pytest.mark.parametrize("value", ["no", "false", 0])
def test_a_flag_that_is_not_a_boolean_is_refused(boat, tmp_path, value):
    config = tmp_path / "exp.yaml"
    config.write_text(yaml.safe_dump({"benchmark": "hpatches", "dataset": {"exclude_large": value},
                                      "methods": [{"matcher": "sift"}]}))
    line = one_line_error(invoke("reproduce", config, "--root", boat, "--out", tmp_path / "out", "--limit", 1))
    assert str(config) in line and "'exclude_large' must be true or false" in line and repr(value) in line
    assert not (tmp_path / "out").exists()


KITTI_RAW = """calib_time: 09-Jan-2012 13:57:47
K_00: 9.842439e+02 0.000000e+00 6.900000e+02 0.000000e+00 9.808141e+02 2.331966e+02 0.000000e+00 0.000000e+00 1.000000e+00
R_00: 1.000000e+00 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00
T_00: 0.000000e+00 0.000000e+00 0.000000e+00
K_01: 9.895267e+02 0.000000e+00 7.020000e+02 0.000000e+00 9.878386e+02 2.455590e+02 0.000000e+00 0.000000e+00 1.000000e+00
R_01: {R01}
T_01: -5.370000e-01 4.822061e-03 -1.252488e-02
"""
ROTATION = "9.993513e-01 1.860866e-02 -3.083487e-02 -1.887662e-02 9.997863e-01 -8.421873e-03 3.067156e-02 8.998467e-03 9.994890e-01"


def stereo_drive(tmp_path: Path, calib: str, odometry: bool = False) -> Path:
    import cv2

    root = tmp_path / ("seq" if odometry else "drive")
    for side in (("image_0", "image_1") if odometry else ("image_00/data", "image_01/data")):
        (root / side).mkdir(parents=True)
        for name in ("000000.png", "000001.png"):
            cv2.imwrite(str(root / side / name), np.full((48, 64, 3), 128, np.uint8))
    (root / ("calib.txt" if odometry else "calib_cam_to_cam.txt")).write_text(calib)
    return root


def test_a_kitti_raw_r01_that_is_not_a_rotation_is_refused(tmp_path):
    skewed = ROTATION.replace("9.993513e-01 1.860866e-02", "9.993513e-01 4.860866e-01")
    root = stereo_drive(tmp_path, KITTI_RAW.format(R01=skewed))
    line = one_line_error(invoke("calibrate", "--root", root, "--out", tmp_path / "out", "--unrectified",
                                 "--matcher", "sift"))
    assert str(root / "calib_cam_to_cam.txt") in line and "'R_01:' is not a rotation" in line
    # the same file with KITTI's own R_01 loads (seven digits are within the tolerance)
    from e3cm_bench.datasets.stereo import load_stereo_sequence

    (root / "calib_cam_to_cam.txt").write_text(KITTI_RAW.format(R01=ROTATION))
    assert load_stereo_sequence(root, unrectified=True).layout == "kitti-raw"


# ----------------------------------------------------------------------------- 12. tracebacks -> one line


def test_a_duplicate_pair_row_in_per_pair_is_refused_by_report(made_run, tmp_path):
    run = run_copy(made_run, tmp_path / "sift")
    rows = pd.read_csv(run / "per_pair.csv")
    pd.concat([rows, rows.iloc[[1]]]).to_csv(run / "per_pair.csv", index=False)
    line = one_line_error(invoke("report", run, "--out", tmp_path / "site"))
    assert str(run / "per_pair.csv") in line and "pair v_boat/1-3 has more than one row" in line


def test_text_in_n_matches_is_refused_by_report(made_run, tmp_path):
    run = run_copy(made_run, tmp_path / "sift")
    rows = pd.read_csv(run / "per_pair.csv").astype({"n_matches": object})
    rows.loc[2, "n_matches"] = "many"
    rows.to_csv(run / "per_pair.csv", index=False)
    line = one_line_error(invoke("report", run, "--out", tmp_path / "site"))
    assert str(run / "per_pair.csv") in line and "column n_matches holds 'many', not a number (pair v_boat/1-4" in line


@pytest.mark.parametrize("method, key", [
    ({"settings": [1, 2]}, "'settings' must be a mapping"),
    ({"label": 123}, "'label' must be non-empty text, got 123"),
    ({"label": ["a", "b"]}, "'label' must be non-empty text"),
    ({"weights": 5}, "'weights' must be non-empty text, got 5"),
    ({"max_side": "big"}, "'max_side' must be a whole number, from 0 to 1,000,000, got 'big'"),
    ({"protocol": ["a"]}, "'protocol' must be non-empty text"),
])
def test_an_experiment_value_of_the_wrong_kind_is_one_line(boat, tmp_path, method, key):
    experiment = {"benchmark": "hpatches", "methods": [{"matcher": "sift"}]}
    if "protocol" in method:
        experiment.update(method)
    else:
        experiment["methods"][0].update(method)
    config = tmp_path / "exp.yaml"
    config.write_text(yaml.safe_dump(experiment))
    line = one_line_error(invoke("reproduce", config, "--root", boat, "--out", tmp_path / "out", "--limit", 1))
    assert str(config) in line and key in line
    if "protocol" not in method:
        assert "methods[0]" in line


def test_ctrl_c_while_the_command_line_loads_is_one_line(tmp_path):
    # Deterministic: the command line's import raises KeyboardInterrupt as a Ctrl-C would in it.
    script = textwrap.dedent("""
        import sys
        class Interrupts:
            def find_spec(self, name, path=None, target=None):
                if name == "e3cm_bench.cli":
                    raise KeyboardInterrupt
        import e3cm_bench.__main__ as entry
        heavy = [m for m in ("pandas", "cv2", "typer", "torch") if m in sys.modules]
        print("loaded before main:", heavy, file=sys.stderr)
        sys.meta_path.insert(0, Interrupts())
        entry.main()
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert done.returncode == 130, done.stderr
    lines = done.stderr.strip().splitlines()
    assert lines[0] == "loaded before main: []"  # the window before the handler is the interpreter's own start
    assert lines[1:] == ["error: interrupted (Ctrl-C) while starting; nothing was done"]


P_LINE = "P{i}: 7.188560e+02 0 6.071928e+02 {tx} 0 7.188560e+02 1.852157e+02 0 0 0 1 0"


def test_calibrate_refuses_one_camera_twice_and_a_key_given_twice_before_matching(tmp_path):
    same = stereo_drive(tmp_path / "a", "\n".join([P_LINE.format(i=0, tx=0), P_LINE.format(i=1, tx=0)]) + "\n", True)
    line = one_line_error(invoke("calibrate", "--root", same, "--out", tmp_path / "o1", "--matcher", "sift"))
    assert str(same / "calib.txt") in line and "P0 and P1 put both cameras at the same place" in line
    twice = stereo_drive(tmp_path / "b", "\n".join([P_LINE.format(i=0, tx=0), P_LINE.format(i=1, tx=-3.8e2),
                                                    P_LINE.format(i=1, tx=0)]) + "\n", True)
    line = one_line_error(invoke("calibrate", "--root", twice, "--out", tmp_path / "o2", "--matcher", "sift"))
    assert str(twice / "calib.txt") in line and "'P1:' is given twice (lines 2 and 3)" in line


# ----------------------------------------------------------------------------- 12. unbounded


def test_an_unused_scene_info_member_is_never_read(shared_data, tmp_path, monkeypatch):
    root = shared_data / "megadepth_test_1500"
    scene = load_scene_info(root / "scene_info" / "kitti00_seq.npz")  # a list whose images the sample holds
    crafted = tmp_path / "scene.npz"
    pair_infos = np.empty(len(scene["pair_infos"]), dtype=object)  # ((i, j), overlap, matches) tuples
    pair_infos[:] = [tuple(p) for p in scene["pair_infos"]]
    np.savez(crafted, **{**scene, "pair_infos": pair_infos})
    # A member no reader needs, 256 MiB once decompressed, a few hundred KiB in the file.
    with zipfile.ZipFile(crafted, "a", compression=zipfile.ZIP_DEFLATED) as archive:
        with archive.open("depth_paths.npy", "w", force_zip64=True) as member:
            header = {"descr": "<f8", "fortran_order": False, "shape": (32 << 20,)}
            np.lib.format.write_array_header_1_0(member, header)
            zeros = bytes(1 << 20)
            for _ in range(256):
                member.write(zeros)
    assert crafted.stat().st_size < 4 << 20
    opened = []
    real_open = zipfile.ZipFile.open

    def spy(self, name, *args, **kwargs):
        opened.append(name.filename if isinstance(name, zipfile.ZipInfo) else name)
        return real_open(self, name, *args, **kwargs)

    monkeypatch.setattr(zipfile.ZipFile, "open", spy)
    result = invoke("megadepth", "--root", root, "--scene-info", crafted, "--out", tmp_path / "run", "--limit", 1, *SIFT)
    assert result.exit_code == 0, result.output
    # the four members a scene_info needs were decompressed, the 256 MiB one never
    assert sorted(set(opened)) == sorted(f"{key}.npy" for key in scene)
    # a member that is read declares more than a scene_info member may hold: refused before reading it
    monkeypatch.setattr(megadepth, "MAX_MEMBER_BYTES", 64)
    line = one_line_error(invoke("megadepth", "--root", root, "--scene-info", crafted, "--out", tmp_path / "run2",
                                 "--limit", 1, *SIFT))
    assert str(crafted) in line and "member image_paths.npy declares" in line


def test_a_small_cache_declaring_gigabytes_is_refused_before_reading(boat, made_run, tmp_path):
    run = run_copy(made_run, tmp_path / "sift")
    n = 375_000_000  # 3 GB of keypoints in each array
    assert n > MAX_PAIR_MATCHES
    with h5py.File(run / "matches.h5", "a") as f:
        group = f["v_boat/1-3"]
        for name, shape in (("keypoints0", (n, 2)), ("keypoints1", (n, 2)), ("scores", (n,))):
            del group[name]
            group.create_dataset(name, shape=shape, dtype="f4", chunks=True, compression="gzip")
    assert (run / "matches.h5").stat().st_size < 1 << 20
    line = one_line_error(invoke("hpatches", "--root", boat, "--out", run, *SIFT, "--eval-only"))
    assert str(run / "matches.h5") in line and "pair v_boat/1-3" in line and "keypoints0 375000000x2" in line


def test_a_cut_block_keeps_the_pairs_hdf5_can_still_read(boat, made_run, tmp_path):
    run = run_copy(made_run, tmp_path / "sift")
    before = {name: MatchCache(made_run / "matches.h5").read(name) for name in MatchCache(made_run / "matches.h5").names()}
    assert len(before) == 5
    os.truncate(run / "matches.h5", (run / "matches.h5").stat().st_size - 2048)
    result = invoke("hpatches", "--root", boat, "--out", run, *SIFT)
    assert result.exit_code == 0, result.output
    # four of the five pairs came back from the cut block; only the lost one was matched again
    assert "5 pairs, 4 already in" in flat(result.output)
    cache = MatchCache(run / "matches.h5")
    assert cache.names() == sorted(before) and cache.damaged == [run / "matches.h5"]
    with h5py.File(run / "matches.001.h5") as again:
        assert [f"v_boat/{k}" for k in again["v_boat"]] == ["v_boat/1-6"]
    for name, matches in before.items():
        assert np.array_equal(cache.read(name).keypoints0, matches.keypoints0), name
    assert pd.read_csv(run / "per_pair.csv").equals(pd.read_csv(made_run / "per_pair.csv"))


# ----------------------------------------------------------------------------- 12. the full-disk estimate


def free_space(monkeypatch, free: int) -> None:
    """Every filesystem reports `free` bytes free (its real size and use otherwise)."""
    real = shutil.disk_usage
    monkeypatch.setattr(shutil, "disk_usage", lambda path: real(path)._replace(free=free))


@pytest.mark.slow  # 25 s alone on a loaded 2-core machine (docs/development.md, Testing)
def test_a_ten_pair_sift_run_needs_what_it_writes_and_stops_in_one_line_where_that_does_not_fit(
        shared_data, tmp_path, monkeypatch):
    """Ten full-size SIFT pairs write about 0.3 MiB. With 1 MiB free the matches fit and the
    reports (a plot bound of 1 MiB) do not: one line before any report, every pair kept. With
    3.7 MiB free (the reported case, once refused as '16.2 MiB needed') the rerun completes."""
    out = tmp_path / "run"
    args = ("hpatches", "--root", shared_data / "hpatches-sequences-release", "--out", out, "--matcher", "sift",
            "--sequences", "v_boat", "--sequences", "v_graffiti")
    with monkeypatch.context() as patch:
        free_space(patch, 1 << 20)
        line = one_line_error(invoke(*args))
    assert f"{out}: not enough free disk space (1.0 MiB free" in line and "needed for the run's reports" in line
    assert not (out / "per_pair.csv").exists() and not (out / "summary.csv").exists()
    assert len(MatchCache(out / "matches.h5").names()) == 10
    with monkeypatch.context() as patch:
        free_space(patch, int(3.7 * (1 << 20)))
        result = invoke(*args)
    assert result.exit_code == 0, result.output
    assert "all 10 pairs found in" in flat(result.output)  # nothing matched again
    assert len(pd.read_csv(out / "per_pair.csv")) == 10
    written = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    assert written < 1 << 20  # what was asked for (reports included) stays above what was written


def test_a_disk_with_no_room_for_one_pair_stops_before_the_first_write(boat, tmp_path, monkeypatch):
    out = tmp_path / "run"
    free_space(monkeypatch, 200 << 10)
    line = one_line_error(invoke("hpatches", "--root", boat, "--out", out, *SIFT))
    assert "not enough free disk space (200.0 KiB free" in line and "needed for the next write" in line
    assert not MatchCache(out / "matches.h5").blocks()


def test_the_reports_room_counts_each_drawing_at_its_images_size(tmp_path):
    from e3cm_bench.datasets.base import Pair
    from e3cm_bench.pipeline.evaluate import PLOT_BYTES, report_bytes

    per_pair = pd.DataFrame({"pair": [f"s/{i}" for i in range(100)], "n_matches": range(100)})
    tables = report_bytes(per_pair, {"n_pairs": 100}, [], [], [])
    assert PLOT_BYTES < tables < PLOT_BYTES + 2000  # 100 short rows: about 1 KiB of CSV
    matches = Matches(np.zeros((1, 2)), np.zeros((1, 2)), None, {"size0": (640, 480), "size1": (320, 600)})
    drawn = report_bytes(per_pair, {"n_pairs": 100}, [], [], [(Pair("s/0", tmp_path, tmp_path), matches)])
    assert 600 * 960 * 3 <= drawn - tables < 600 * 960 * 3 + (16 << 10)
