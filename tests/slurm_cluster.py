"""A real one-node SLURM cluster for the tests (tests/pipeline/test_slurm_cluster.py): one that already
answers (`sinfo`), or one that scripts/slurm/local_cluster.sh starts (root; it installs
slurm-wlm and munge with apt-get where absent) and stops at the end of the session.

Where none can start, the tests skip with the reason in one line, except where
E3CM_REQUIRE_SLURM=1 (.ci/run sets it after starting the cluster): there they fail."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "slurm" / "local_cluster.sh"


@dataclass(frozen=True)
class Cluster:
    version: str
    partition: str  # the default partition
    started: bool  # by this fixture (stopped at the end)


def answers() -> bool:
    try:
        return subprocess.run(["sinfo", "-h"], capture_output=True, timeout=20).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


def _unavailable(reason: str):
    if os.environ.get("E3CM_REQUIRE_SLURM") == "1":
        pytest.fail(f"E3CM_REQUIRE_SLURM=1 but {reason}")
    pytest.skip(reason)


@pytest.fixture(scope="session")
def slurm_cluster():
    started = False
    if not answers():
        if os.geteuid() != 0:
            _unavailable("no SLURM controller answers (sinfo) and not root: cannot start one "
                         "(sudo scripts/slurm/local_cluster.sh start)")
        if not shutil.which("slurmctld") and not shutil.which("apt-get"):
            _unavailable("no SLURM controller answers (sinfo), SLURM is not installed and there is no apt-get")
        done = subprocess.run([str(SCRIPT), "start"], capture_output=True, text=True, timeout=900)
        if done.returncode != 0 or not answers():
            why = (done.stderr.strip().splitlines() or ["no message"])[-1]
            _unavailable(f"the local SLURM cluster did not start: {why}")
        started = True
    version = subprocess.run(["sinfo", "--version"], capture_output=True, text=True, timeout=20).stdout.strip()
    partitions = subprocess.run(["sinfo", "-h", "-o", "%P"], capture_output=True, text=True, timeout=20).stdout.split()
    default = next((p.rstrip("*") for p in partitions if p.endswith("*")), partitions[0] if partitions else "")
    try:
        yield Cluster(version=version, partition=default, started=started)
    finally:
        if started:
            subprocess.run([str(SCRIPT), "stop"], capture_output=True, timeout=120)


def job_states(job_id: str) -> dict[str, str]:
    """{array task id (or the job id): JobState} of a job the controller still holds."""
    text = subprocess.run(["scontrol", "-o", "show", "job", str(job_id)], capture_output=True, text=True,
                          timeout=30).stdout
    states = {}
    for line in text.splitlines():
        fields = dict(re.findall(r"(\w+)=(\S*)", line))
        states[fields.get("ArrayTaskId") or fields["JobId"]] = fields["JobState"]
    return states


def job_lines(job_id: str) -> list[str]:
    """One line per task: id, name, state, exit code, time limit, run time (for a failing test's message)."""
    text = subprocess.run(["scontrol", "-o", "show", "job", str(job_id)], capture_output=True, text=True,
                          timeout=30).stdout
    keys = ("JobId", "ArrayJobId", "ArrayTaskId", "JobName", "JobState", "Reason", "ExitCode", "TimeLimit", "RunTime")
    return [" ".join(f"{k}={v}" for k, v in re.findall(r"(\w+)=(\S*)", line) if k in keys) for line in text.splitlines()]


def wait_for(job_id: str, timeout: float = 600) -> dict[str, str]:
    """Wait until no task of the job is pending or running; its tasks' states."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        states = job_states(job_id)
        if states and not any(s in ("PENDING", "RUNNING", "CONFIGURING", "COMPLETING", "SUSPENDED")
                              for s in states.values()):
            return states
        time.sleep(1)
    subprocess.run(["scancel", str(job_id)], timeout=30)
    raise AssertionError(f"SLURM job {job_id} still running after {timeout} s: {job_lines(job_id)}")
