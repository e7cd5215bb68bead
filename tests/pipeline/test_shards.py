"""Runs that outgrow one machine: shards, merge, launchers."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from e3cm_bench.pipeline.shards import parse_shard, shard_slice
from helpers import flat, invoke, one_line_error, same_csvs, same_tables

LITE = ["--backbone", "efficientnet_lite0"]


def command(*args) -> list[str]:
    return [sys.executable, "-m", "e3cm_bench.cli", *map(str, args)]


@pytest.fixture(scope="module")
def deep_args(shared_data):
    return ["hpatches", "--root", shared_data / "hpatches-sequences-release", "--matcher", "direct", *LITE,
            "--max-side", 320]


@pytest.fixture(scope="module")
def reference(deep_args, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("reference") / "run"
    done = subprocess.run(command(*deep_args, "--out", out), capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    return out


def test_shard_slices_cover_the_pairs_once():
    for n_pairs in (0, 1, 7, 15, 1500):
        for n in (1, 2, 3, 8):
            covered = [i for k in range(1, n + 1) for i in range(n_pairs)[shard_slice(n_pairs, (k, n))]]
            assert covered == list(range(n_pairs))
    assert parse_shard("2/3") == (2, 3)
    for bad in ("0/3", "4/3", "2", "a/b"):
        with pytest.raises(ValueError, match="--shard"):
            parse_shard(bad)


@pytest.mark.slow  # 82 s, and its reference run's 50 s alone on a loaded 2-core machine (docs/development.md, Testing)
def test_three_concurrent_shards_merge_to_the_unsharded_csvs(deep_args, reference, tmp_path):
    """Real processes started together; the last to finish merges; the result is byte-identical."""
    out = tmp_path / "run"
    processes = [subprocess.Popen(command(*deep_args, "--out", out, "--shard", f"{k}/3"), stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True) for k in (1, 2, 3)]
    for process in processes:
        _, err = process.communicate(timeout=600)
        assert process.returncode == 0, err
    same_csvs(out, reference)
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["shards"]["count"] == 3 and set(config["shards"]["timing"]) == {"1-of-3", "2-of-3", "3-of-3"}
    assert config["timing"]["pairs_matched"] == 15
    assert Path(config["dataset_load"]["root"]).is_absolute()  # a merge may run from another directory
    assert [yaml.safe_load((out / "shards" / f"{k}-of-3" / "config.yaml").read_text())["shard"]["n_pairs"]
            for k in (1, 2, 3)] == [5, 5, 5]
    # merge by hand gives the same files again
    assert invoke("merge", out).exit_code == 0
    same_csvs(out, reference)


def test_a_missing_shard_is_named(shared_data, tmp_path):
    out = tmp_path / "run"
    args = ["hpatches", "--root", shared_data / "hpatches-sequences-release", "--matcher", "sift", "--max-side", 320,
            "--out", out]
    assert invoke(*args, "--shard", "2/3").exit_code == 0
    assert not (out / "summary.csv").exists()  # not merged: shards 1 and 3 are missing
    line = one_line_error(invoke("merge", out))
    assert "1-of-3, 3-of-3 missing" in line and "--shard K/3" in line


@pytest.mark.slow  # 34 s in the fast set under a load of about 7 on the shared 2-core machine (docs/development.md, Testing)
def test_a_shard_of_another_method_is_refused(shared_data, tmp_path):
    out = tmp_path / "run"
    common = ["hpatches", "--root", shared_data / "hpatches-sequences-release", "--max-side", 320, "--out", out]
    assert invoke(*common, "--matcher", "sift", "--shard", "1/2").exit_code == 0
    result = invoke(*common, "--matcher", "direct", *LITE, "--shard", "2/2")
    line = one_line_error(result)  # the last shard tries to merge and finds two identities
    assert "2-of-2" in line and "identity" in line
    assert not (out / "summary.csv").exists()


@pytest.mark.slow  # 21 s alone on a loaded 2-core machine (docs/development.md, Testing)
def test_submitit_launcher_runs_locally_without_slurm(shared_data, tmp_path, monkeypatch):
    submitit = pytest.importorskip("submitit")
    # submitit picks SLURM wherever srun is on PATH (tests/pipeline/test_slurm_cluster.py runs that case)
    monkeypatch.setattr(submitit.SlurmExecutor, "affinity", classmethod(lambda cls: -1))
    out, reference = tmp_path / "run", tmp_path / "reference"
    args = ["hpatches", "--root", shared_data / "hpatches-sequences-release", "--matcher", "sift", "--max-side", 320]
    assert invoke(*args, "--out", reference).exit_code == 0
    result = invoke(*args, "--out", out, "--launcher", "slurm", "--shards", 2)
    assert result.exit_code == 0 and "submitted 2 shard(s) to local" in flat(result.output)
    same_csvs(out, reference)
    assert (out / "shards" / "slurm").is_dir()  # submitit's logs and pickles


@pytest.mark.slow  # 29 s in the fast set under a load of about 7 on the shared 2-core machine (docs/development.md, Testing)
def test_workers_run_shards_in_parallel_processes(shared_data, tmp_path):
    out, reference = tmp_path / "run", tmp_path / "reference"
    args = ["hpatches", "--root", shared_data / "hpatches-sequences-release", "--matcher", "sift", "--max-side", 320]
    assert invoke(*args, "--out", reference).exit_code == 0
    result = invoke(*args, "--out", out, "--workers", 2)
    assert result.exit_code == 0 and "2 shards merged" in flat(result.output)
    same_csvs(out, reference)
    line = one_line_error(invoke(*args, "--out", tmp_path / "x", "--workers", 2, "--shard", "1/2"))
    assert "--shard and --workers do not go together" in line


@pytest.mark.slow  # 30 s alone on a loaded 2-core machine (docs/development.md, Testing)
def test_sharded_reproduce_writes_the_table_when_the_last_shard_ends(shared_data, tmp_path):
    config = tmp_path / "exp.yaml"
    config.write_text(yaml.safe_dump({"benchmark": "hpatches", "max_side": 320, "methods": [
        {"label": "sift", "matcher": "sift"}, {"label": "sift-tight", "matcher": "sift"}]}))
    root = shared_data / "hpatches-sequences-release"
    whole, sharded = tmp_path / "whole", tmp_path / "sharded"
    assert invoke("reproduce", config, "--root", root, "--out", whole, "--no-compare").exit_code == 0
    first = invoke("reproduce", config, "--root", root, "--out", sharded, "--no-compare", "--shard", "1/2")
    assert first.exit_code == 0 and "table is written when every method's shards are" in flat(first.output)
    assert not (sharded / "table.csv").exists()
    assert invoke("reproduce", config, "--root", root, "--out", sharded, "--no-compare", "--shard", "2/2").exit_code == 0
    same_tables(sharded / "table.csv", whole / "table.csv")
    (sharded / "table.csv").unlink()
    assert invoke("merge", sharded, "--no-compare").exit_code == 0  # merge of a whole experiment
    same_tables(sharded / "table.csv", whole / "table.csv")
