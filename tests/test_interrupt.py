"""Ctrl-C stops the test suite at once (tests/conftest.py): a SIGINT while a test runs a command
in-process ends the session after that test, instead of failing the test on the command's exit
status 130 and going on with the next one."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

TESTS = Path(__file__).resolve().parent
REPO = TESTS.parent

SLEEPY = '''
import time
from pathlib import Path

import e3cm_bench.pipeline.experiments as experiments
from helpers import invoke


def sleepy(marker):
    def write_table(*args, **kwargs):
        Path(marker).write_text("started")
        time.sleep(120)
    return write_table


def test_first(monkeypatch, tmp_path):
    monkeypatch.setattr(experiments, "write_table", sleepy(Path(__file__).with_name("first")))
    assert invoke("table", tmp_path, "--out", tmp_path / "t").exit_code == 0


def test_second(monkeypatch, tmp_path):
    monkeypatch.setattr(experiments, "write_table", sleepy(Path(__file__).with_name("second")))
    assert invoke("table", tmp_path, "--out", tmp_path / "t").exit_code == 0
'''


def test_ctrl_c_stops_the_suite_during_an_in_process_command(tmp_path):
    (tmp_path / "test_sleepy.py").write_text(SLEEPY)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), str(REPO), os.environ.get("PYTHONPATH", "")])}
    # this suite's conftest as a plugin, on a test file outside it (and none of the project's settings)
    process = subprocess.Popen([sys.executable, "-m", "pytest", "-q", "-p", "conftest", "-p", "no:cacheprovider",
                                "-c", os.devnull, "--rootdir", str(tmp_path), "test_sleepy.py"],
                               cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 300
        while not (tmp_path / "first").exists() and process.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        assert (tmp_path / "first").exists(), process.communicate(timeout=60)[0] if process.poll() is not None else ""
        time.sleep(0.5)
        process.send_signal(signal.SIGINT)
        output, _ = process.communicate(timeout=60)  # the second test would sleep 120 s
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert not (tmp_path / "second").exists(), output
    assert process.returncode == 2, output  # pytest's "interrupted"
    assert "Interrupted: interrupted (Ctrl-C)" in output, output
