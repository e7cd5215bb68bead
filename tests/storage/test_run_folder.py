"""The run folder's owner (run.RunFolder), the generated benchmark commands, and what a run
does with a matcher that fails on some pairs (--on-matcher-error, --pair-timeout) or with
matches whose record is gone."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from e3cm_bench.benchmarks import BENCHMARKS
from e3cm_bench.storage.cache import MatchCache
from e3cm_bench.datasets.sources import default_sources
from e3cm_bench.matchers import MatcherEntry, register, unregister
from e3cm_bench.ground.matches import Matches
from e3cm_bench.storage import FAILED_ATTR, RunConfig, RunFolder
from e3cm_bench.pipeline.match_options import MatchOptions
from helpers import flat, invoke, one_line_error

SIFT = ("--matcher", "sift", "--max-side", 320)


@pytest.fixture(scope="module")
def boat(shared_data, tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("data") / "hpatches"
    shutil.copytree(shared_data / "hpatches-sequences-release" / "v_boat", root / "v_boat")
    return root


class FailsOn:
    """A matcher that raises (or first sleeps) on its second pair."""

    def __init__(self, how: str) -> None:
        self.name, self.how, self.calls = f"fails-on-{how}", how, 0

    def match(self, image0: np.ndarray, image1: np.ndarray) -> Matches:
        self.calls += 1
        if self.calls == 2:
            if self.how == "sleep":
                time.sleep(30)
            raise RuntimeError("cannot match this one")
        h, w = image0.shape[:2]
        points = np.array([[w * 0.25, h * 0.25], [w * 0.5, h * 0.5], [w * 0.75, h * 0.25], [w * 0.3, h * 0.7]], np.float32)
        return Matches(points, points.copy(), np.ones(len(points), np.float32))


@pytest.fixture
def failing_matcher():
    made = []

    def make(how: str) -> str:
        name = f"fails-on-{how}"
        register(MatcherEntry(name, "fails on its second pair", build=lambda s: FailsOn(how), origin="test"))
        made.append(name)
        return name

    yield make
    for name in made:
        unregister(name)


def test_a_run_writes_only_where_its_folder_says(boat, tmp_path):
    out = tmp_path / "run"
    assert invoke("hpatches", "--root", boat, "--out", out, *SIFT, "--limit", 2).exit_code == 0
    folder = RunFolder(out)
    for path in (folder.config_path, folder.matches_path, folder.per_pair_path, folder.summary_path):
        assert path.is_file(), path
    assert not folder.failures_path.exists() and not folder.skipped_path.exists() and not folder.spill_dir.exists()
    config = folder.run_config().record  # as written, in its order
    # the record's blocks in RunConfig's order; the optional ones only where they apply
    assert list(config)[:10] == ["benchmark", "method", "identity", "matcher", "device", "dataset", "evaluation",
                                 "versions", "environment", "timing"]
    assert "allocator" in config["environment"] and "shard" not in config and "imported_files" not in config
    assert config["dataset_load"]["root"] == str(boat.resolve())
    assert [f.path for f in RunFolder.find(tmp_path)] == [out]  # found below a folder, as check finds runs
    assert RunConfig.from_dict(config).as_dict() == config  # the record reads back as it was written


def test_matches_without_their_record_are_not_resumed(boat, tmp_path):
    out = tmp_path / "run"
    assert invoke("hpatches", "--root", boat, "--out", out, *SIFT, "--limit", 2).exit_code == 0
    RunFolder(out).config_path.unlink()  # the record is gone: what made these matches is unknown
    line = one_line_error(invoke("hpatches", "--root", boat, "--out", out, *SIFT, "--limit", 3))
    assert "matches.h5: holds the matches of 2 pairs but config.yaml is missing" in line and "--overwrite" in line
    # an import into such a folder is refused the same way, before anything is written
    npz = tmp_path / "npz"
    (npz / "v_boat").mkdir(parents=True)
    for k in (2, 3):
        np.savez(npz / "v_boat" / f"1-{k}.npz", keypoints0=np.zeros((0, 2)), keypoints1=np.zeros((0, 2)))
    line = one_line_error(invoke("import", "hpatches", "--root", boat, "--out", out, "--npz", npz, "--limit", 2))
    assert "config.yaml is missing" in line
    assert len(MatchCache(out / "matches.h5").names()) == 2
    # --overwrite replaces them
    assert invoke("hpatches", "--root", boat, "--out", out, *SIFT, "--limit", 2, "--overwrite").exit_code == 0


def test_a_failing_pair_stops_the_run_by_default_and_says_how_to_go_on(boat, tmp_path, failing_matcher):
    name = failing_matcher("raise")
    out = tmp_path / "run"
    line = one_line_error(invoke("hpatches", "--root", boat, "--out", out, "--matcher", name))
    assert f"matcher {name} raised RuntimeError: cannot match this one" in line
    assert "--on-matcher-error fail-pair" in line
    assert len(MatchCache(out / "matches.h5").names()) == 1  # the pair before it is kept


def test_fail_pair_counts_the_pair_as_failed_lists_it_and_goes_on(boat, tmp_path, failing_matcher):
    name = failing_matcher("raise")
    out = tmp_path / "run"
    result = invoke("hpatches", "--root", boat, "--out", out, "--matcher", name, "--on-matcher-error", "fail-pair")
    assert result.exit_code == 0, flat(result.output)
    folder = RunFolder(out)
    failures = pd.read_csv(folder.failures_path)
    assert len(failures) == 1 and "cannot match this one" in failures["error"].iloc[0]
    failed = failures["pair"].iloc[0]
    summary = pd.read_csv(folder.summary_path).iloc[0]
    per_pair = pd.read_csv(folder.per_pair_path).set_index("pair")
    assert summary["n_failed"] == 1 and summary["n_pairs"] == 5  # counted, not left out
    assert per_pair.loc[failed, "n_matches"] == 0 and np.isinf(per_pair.loc[failed, "h_error"])
    assert MatchCache(out / "matches.h5").read(failed).info[FAILED_ATTR].startswith(f"matcher {name} raised")
    # a resume keeps the failure (it is not matched again) and writes the same files
    before = folder.per_pair_path.read_bytes()
    again = invoke("hpatches", "--root", boat, "--out", out, "--matcher", name, "--on-matcher-error", "fail-pair")
    assert again.exit_code == 0 and "all 5 pairs found" in flat(again.output)
    assert folder.per_pair_path.read_bytes() == before and folder.failures_path.is_file()


def test_pair_timeout_fails_a_pair_that_takes_too_long(boat, tmp_path, failing_matcher):
    name = failing_matcher("sleep")
    out = tmp_path / "run"
    t = time.perf_counter()
    result = invoke("hpatches", "--root", boat, "--out", out, "--matcher", name, "--limit", 3,
                    "--on-matcher-error", "fail-pair", "--pair-timeout", 1)
    assert result.exit_code == 0, flat(result.output)
    assert time.perf_counter() - t < 25  # the 30 s sleep was cut short
    failures = pd.read_csv(RunFolder(out).failures_path)
    assert len(failures) == 1 and name in failures["error"].iloc[0]
    assert "1" in failures["error"].iloc[0]  # the limit is named


@pytest.mark.parametrize("bad, says", [(("--on-matcher-error", "skip"), "--on-matcher-error must be one of stop, fail-pair"),
                                       (("--pair-timeout", 0), "--pair-timeout must be a positive number")])
def test_match_options_are_checked_in_one_line(boat, tmp_path, bad, says):
    line = one_line_error(invoke("hpatches", "--root", boat, "--out", tmp_path / "run", *SIFT, *bad))
    assert says in line
    with pytest.raises(ValueError):
        MatchOptions(on_matcher_error="skip")


def test_every_benchmark_has_its_command_with_its_own_dataset_options():
    from e3cm_bench.cli import app
    from typer.main import get_command

    commands = get_command(app).commands
    for name, bench in BENCHMARKS.items():
        assert name in commands, name
        flags = {opt for param in commands[name].params for opt in param.opts}
        assert {"--out", "--matcher", "--limit", "--shard", "--workers", "--on-matcher-error"} <= flags
        assert {option.flag for option in bench.command_options()} <= flags
        others = {o.flag for b in BENCHMARKS.values() if b is not bench for o in b.command_options()}
        assert not (others - {o.flag for o in bench.command_options()}) & flags  # no other benchmark's options
    import_flags = {opt for param in commands["import"].params for opt in param.opts}
    assert {o.flag for b in BENCHMARKS.values() for o in b.command_options()} <= import_flags


def test_a_benchmark_without_a_data_source_asks_for_its_root():
    with pytest.raises(ValueError, match="no data source is known for toy: pass --root"):
        default_sources("toy")


def test_an_option_of_another_benchmark_is_refused_by_import(boat, tmp_path):
    line = one_line_error(invoke("import", "hpatches", "--root", boat, "--out", tmp_path / "run", "--npz", tmp_path,
                                 "--pairs", tmp_path / "pairs.txt"))
    assert "--pairs do(es) not apply to hpatches" in line


def test_calibrate_and_a_run_share_one_record(tmp_path):
    """The calibration's config.yaml is a RunConfig too: the environment block, the allocator in it."""
    config = RunConfig(benchmark=None, method="sift", identity={"matcher": "sift"}, command="calibrate",
                       sequence={"root": "x"}, calibration={"frames": [1]}, environment=RunConfig.environment_now())
    RunFolder(tmp_path).write_config(config)
    record = yaml.safe_load(RunFolder(tmp_path).config_path.read_text())
    assert record["command"] == "calibrate" and "allocator" in record["environment"] and "allocator" not in record
