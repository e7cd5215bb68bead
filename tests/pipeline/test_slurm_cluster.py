"""The SLURM launcher and scripts/slurm/array.sh against a real one-node SLURM cluster:
real arrays, scancel and the time limit, on 6 pairs of the shared HPatches sample with SIFT.

The matcher is tests/slurm_slow_matcher.py (SIFT after E3CM_SLOW_SECONDS per pair, 0 unless
a test sets it), so that a task is still running when a test cancels it or its time limit passes;
every run merges to the bytes of the one unsharded run made without the wait."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
import yaml

from e3cm_bench.storage.folder import RunFolder
from helpers import same_csvs, same_tables
from slurm_cluster import job_lines, slurm_cluster, wait_for  # noqa: F401 - slurm_cluster is a fixture

# The tests that need the cluster: starting it (about 25 s) and its real arrays, cancels and time
# limits took 164 s together, the time limit alone 86 s.
slow = pytest.mark.slow

TESTS = Path(__file__).resolve().parents[1]  # tests/: slurm_slow_matcher.py lies there
REPO = TESTS.parent
ARRAY = REPO / "scripts" / "slurm" / "array.sh"
MATCHER = "slurm_slow_matcher:ENTRY"
N_PAIRS = 6


@pytest.fixture(scope="module")
def env(slurm_cluster):
    """The environment of every command: the tasks get it from sbatch (--export=ALL) and find
    this Python's e3cm-bench and the test matcher."""
    path = os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")])
    python_path = os.pathsep.join(p for p in [str(TESTS), str(REPO), os.environ.get("PYTHONPATH")] if p)
    return {**os.environ, "PATH": path, "PYTHONPATH": python_path, "E3CM_SLOW_SECONDS": "0"}


@pytest.fixture(scope="module")
def args(shared_data):
    return ["hpatches", "--root", str(shared_data / "hpatches-sequences-release"), "--matcher", MATCHER,
            "--max-side", "320", "--limit", str(N_PAIRS)]


def cli(*args) -> list[str]:
    return [sys.executable, "-m", "e3cm_bench.cli", *map(str, args)]


def run(command, env, cwd, timeout=600, **changes) -> subprocess.CompletedProcess:
    done = subprocess.run(command, cwd=cwd, env={**env, **changes}, capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, (command, done.stdout[-2000:], done.stderr[-2000:])
    return done


@pytest.fixture(scope="module")
def reference(args, env, tmp_path_factory) -> Path:
    """The same run, unsharded, in this process's machine (no SLURM)."""
    out = tmp_path_factory.mktemp("reference") / "run"
    run(cli(*args, "--out", out), env, out.parent)
    return out


def sbatch(options: list[str], command: list[str], env, cwd, **changes) -> str:
    """Submit; the job id. (Not sbatch --wait: it polls at growing intervals, up to half a
    minute late; wait_for asks every second.)"""
    done = run(["sbatch", "--parsable", *options, *command], env, cwd, **changes)
    return done.stdout.strip().split(";")[0]


def array_options(cluster, tmp_path, array: str, time_limit: str = "10") -> list[str]:
    """array.sh's #SBATCH lines (partition gpu, a GPU, 8 CPUs, 32G) overridden for this node."""
    return [f"--partition={cluster.partition}", "--gres=none", "--cpus-per-task=1", "--mem=1G",
            f"--time={time_limit}", f"--array={array}", f"--output={tmp_path}/slurm-%A_%a.out"]


def cached(out: Path, shard: str) -> int:
    """Pairs in a shard's match cache (written by atomic renames: readable while a task runs)."""
    folder = RunFolder(out / "shards" / shard)
    return len(folder.cache().names()) if folder.matches_path.is_file() else 0


def shard_config(out: Path, shard: str) -> dict:
    return yaml.safe_load((out / "shards" / shard / "config.yaml").read_text())


def test_a_shard_records_the_command_that_reruns_it():
    """Without a cluster: the launch options of the command line become --shard K/N."""
    from e3cm_bench.pipeline.shards import shard_command

    for argv in (["/venv/bin/e3cm-bench", "hpatches", "--out", "my runs", "--launcher", "slurm", "--shards", "4"],
                 ["/src/e3cm_bench/cli/__main__.py", "hpatches", "--out", "my runs", "--launcher=slurm", "--shards=4"],
                 ["e3cm-bench", "hpatches", "--workers", "4", "--out", "my runs"],
                 ["e3cm-bench", "hpatches", "--out", "my runs", "--shard", "1/4"]):
        assert shard_command((3, 4), argv, cwd="/w d") == "cd '/w d' && e3cm-bench hpatches --out 'my runs' --shard 3/4"
    assert shard_command((1, 2), ["e3cm-bench", "hpatches", "--devices", "cuda:0,cuda:1"], cwd="/w",
                         device="cuda:0") == "cd /w && e3cm-bench hpatches --shard 1/2 --device cuda:0"
    assert shard_command((1, 2), ["/usr/bin/pytest", "tests"]) is None  # the Python API: no command line to name


@slow
def test_launcher_slurm_submits_a_real_array(slurm_cluster, args, env, reference, tmp_path):
    out = tmp_path / "run"
    # SBATCH_TIMELIMIT overrides the --time=1440 of the script submitit writes (docs/cluster.md)
    done = run(cli(*args, "--out", out, "--launcher", "slurm", "--shards", 2), env, tmp_path, SBATCH_TIMELIMIT="10")
    text = " ".join(done.stdout.split())
    assert "submitted 2 shard(s) to slurm" in text, text
    job = re.search(r"to slurm: job (\d+)", text).group(1)
    states = wait_for(job)
    assert states == {"0": "COMPLETED", "1": "COMPLETED"}, job_lines(job)
    assert all("TimeLimit=00:10:00" in line for line in job_lines(job)), job_lines(job)
    same_csvs(out, reference)
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["shards"]["count"] == 2 and config["timing"]["pairs_matched"] == N_PAIRS
    logs = out / "shards" / "slurm"
    script = (logs / f"{job}_submission.sh").read_text()
    assert "#SBATCH --array=0-1%2" in script and "#SBATCH --job-name=e3cm-bench" in script
    for task in (0, 1):
        assert "Job completed successfully" in (logs / f"{job}_{task}_0_log.out").read_text()
    # each shard records the command that reruns it alone: the launch options become --shard K/2
    command = shard_config(out, "2-of-2")["shard"]["command"]
    assert command.endswith(f"--out {out} --shard 2/2") and "--launcher" not in command and "--shards" not in command


@slow
def test_array_script_runs_and_merges(slurm_cluster, args, env, reference, tmp_path):
    out = tmp_path / "run"
    job = sbatch(array_options(slurm_cluster, tmp_path, "1-2"), [str(ARRAY), *args, "--out", out],
                 env, tmp_path, E3CM_SHARDS="2")
    assert wait_for(job) == {"1": "COMPLETED", "2": "COMPLETED"}, job_lines(job)
    same_csvs(out, reference)
    assert sorted(p.name for p in tmp_path.glob(f"slurm-{job}_*.out")) == [f"slurm-{job}_1.out", f"slurm-{job}_2.out"]


@slow
def test_array_task_outside_the_shards_is_refused(slurm_cluster, args, env, tmp_path):
    job = sbatch(array_options(slurm_cluster, tmp_path, "3"), [str(ARRAY), *args, "--out", tmp_path / "run"], env,
                 tmp_path, E3CM_SHARDS="2")
    assert wait_for(job) == {"3": "FAILED"}, job_lines(job)
    log = (tmp_path / f"slurm-{job}_3.out").read_text().strip().splitlines()
    assert log == ["array.sh: array task 3 is not a shard of 1..2 (--array=1-N with N = E3CM_SHARDS, 2)"]
    assert not (tmp_path / "run").exists()


@slow
def test_a_cancelled_task_resubmitted_resumes(slurm_cluster, args, env, reference, tmp_path):
    out = tmp_path / "run"
    command = [str(ARRAY), *args, "--out", str(out)]
    job = sbatch(array_options(slurm_cluster, tmp_path, "1-2"), command, env, tmp_path,
                 E3CM_SHARDS="2", E3CM_SLOW_SECONDS="4")
    end = time.monotonic() + 300
    while cached(out, "1-of-2") < 1:  # one pair matched, the next one waiting: cancel task 1
        assert time.monotonic() < end, job_lines(job)
        time.sleep(0.5)
    subprocess.run(["scancel", f"{job}_1"], check=True, timeout=30)
    states = wait_for(job)
    assert states == {"1": "CANCELLED", "2": "COMPLETED"}, job_lines(job)
    before = cached(out, "1-of-2")
    assert 1 <= before < N_PAIRS // 2 and not shard_config(out, "1-of-2")["shard"]["complete"]
    assert not (out / "summary.csv").exists()
    # array.sh's rerun of one shard: an array of one task, still shard 1 of 2
    again = sbatch(array_options(slurm_cluster, tmp_path, "1"), command, env, tmp_path, E3CM_SHARDS="2")
    assert wait_for(again) == {"1": "COMPLETED"}, job_lines(again)
    log = " ".join((tmp_path / f"slurm-{again}_1.out").read_text().split())
    assert f"{N_PAIRS // 2} pairs, {before} already in" in log  # it resumed: only the others were matched
    same_csvs(out, reference)


@slow
def test_a_task_past_its_time_limit_is_named_by_merge_and_resumes(slurm_cluster, args, env, reference, tmp_path):
    out = tmp_path / "run"
    command = [str(ARRAY), *args, "--out", str(out)]
    # shard 1: 40 s a pair, 3 pairs, a time limit of 1 minute (SLURM's smallest; slurmctld looks
    # every 30 s, so the task ends 60 to 90 s in); shard 2 at the same time, with no wait
    first = sbatch(array_options(slurm_cluster, tmp_path, "1", time_limit="1"), command, env, tmp_path,
                   E3CM_SHARDS="2", E3CM_SLOW_SECONDS="40")
    second = sbatch(array_options(slurm_cluster, tmp_path, "2"), command, env, tmp_path, E3CM_SHARDS="2")
    assert wait_for(second) == {"2": "COMPLETED"}, job_lines(second)
    assert wait_for(first, timeout=300) == {"1": "TIMEOUT"}, job_lines(first)
    assert "DUE TO TIME LIMIT" in (tmp_path / f"slurm-{first}_1.out").read_text()  # slurmstepd's line
    before = cached(out, "1-of-2")
    assert before < N_PAIRS // 2 and not shard_config(out, "1-of-2")["shard"]["complete"]
    merge = subprocess.run(cli("merge", out), env=env, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert merge.returncode == 2 and not (out / "summary.csv").exists()
    line = " ".join(merge.stderr.split())
    assert "1-of-2 not finished" in line, line
    rerun = line.split("it resumes what it matched: ", 1)[1]
    assert rerun.startswith(f"cd {tmp_path} && e3cm-bench hpatches ") and rerun.endswith("--shard 1/2"), rerun
    # the command merge names, as a SLURM job of its own, resumes the shard and merges the run
    again = sbatch([f"--partition={slurm_cluster.partition}", "--time=10", f"--output={tmp_path}/rerun.out",
                    "--wrap", rerun], [], env, tmp_path)
    assert wait_for(again) == {again: "COMPLETED"}, job_lines(again)
    log = " ".join((tmp_path / "rerun.out").read_text().split())
    assert f"{N_PAIRS // 2} pairs, {before} already in" in log
    same_csvs(out, reference)


@slow
def test_reproduce_with_the_slurm_launcher(slurm_cluster, shared_data, env, tmp_path):
    config = tmp_path / "exp.yaml"
    config.write_text(yaml.safe_dump({"benchmark": "hpatches", "max_side": 320, "methods": [
        {"label": "sift", "matcher": "sift"}, {"label": "slow", "matcher": MATCHER}]}))
    common = [config, "--root", shared_data / "hpatches-sequences-release", "--limit", N_PAIRS, "--no-compare"]
    whole, sharded = tmp_path / "whole", tmp_path / "sharded"
    run(cli("reproduce", *common, "--out", whole), env, tmp_path)
    done = run(cli("reproduce", *common, "--out", sharded, "--launcher", "slurm", "--shards", 2), env, tmp_path)
    job = re.search(r"to slurm: job (\d+)", " ".join(done.stdout.split())).group(1)
    assert wait_for(job) == {"0": "COMPLETED", "1": "COMPLETED"}, job_lines(job)
    # the last task to finish merged both methods and wrote the table
    same_tables(sharded / "table.csv", whole / "table.csv")
    runs = [p for p in sharded.iterdir() if (p / "shards").is_dir()]
    assert len(runs) == 2 and all(yaml.safe_load((p / "config.yaml").read_text())["shards"]["count"] == 2 for p in runs)
    assert pd.read_csv(sharded / "table.csv")["method"].tolist() == pd.read_csv(whole / "table.csv")["method"].tolist()
