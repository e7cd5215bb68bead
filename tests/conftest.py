"""Shared fixtures: the real benchmark samples in ../shared/data (skip cleanly without them)."""

from __future__ import annotations

import signal
import sys
import threading
from pathlib import Path

import pytest

# The test modules sit in subfolders by subject; helpers.py, http_server.py and slurm_cluster.py
# sit here, in tests/, and are imported by name from every subfolder, whatever the import mode.
TESTS = Path(__file__).resolve().parent
if str(TESTS) not in sys.path:
    sys.path.insert(0, str(TESTS))

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"


# Ctrl-C stops the suite at once. Most tests run a command in-process (helpers.invoke), and a
# command turns a KeyboardInterrupt into its exit status 130 (cli/common.friendly_errors: the
# user's Ctrl-C of a run) or click into "Aborted!": the running test failed on that status and
# pytest went on with the next test, so each Ctrl-C cost one test. A SIGINT is noted here (and
# raised as ever), and the session stops when that test ends.
_SIGINTS: list[int] = []


def _on_sigint(signum, frame):
    _SIGINTS.append(signum)
    signal.default_int_handler(signum, frame)


def pytest_configure(config):
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, _on_sigint)


def pytest_unconfigure(config):
    if threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGINT) is _on_sigint:
        signal.signal(signal.SIGINT, signal.default_int_handler)


# The smoke set (`python -m pytest -q -m smoke`, the README's): these files' fast tests, about
# 250 tests in under a minute on 2 cores: the package imports and starts, the public API, the
# metrics, geometry and estimators, the statistics, a real SIFT run on the shared sample and what
# guards its folder, the registry, the old import paths, hostile plugin returns, the table.
SMOKE_FILES = ("test_startup.py", "test_api.py", "test_moved_imports.py", "benchmarks/test_metrics.py",
               "benchmarks/test_geometry.py", "benchmarks/test_estimator_backends.py",
               "benchmarks/test_sfm_bags_interval.py", "reporting/test_stats.py", "reporting/test_own_files.py",
               "reporting/test_table_shape.py", "cli/test_cli_messages.py", "storage/test_run_config.py",
               "matching/test_matcher_registry.py", "pipeline/test_hostile_plugin_returns.py")


def pytest_collection_modifyitems(config, items):
    tests = Path(__file__).resolve().parent
    missing = [name for name in SMOKE_FILES if not (tests / name).is_file()]
    assert not missing, f"tests/conftest.py SMOKE_FILES names files that are gone: {missing}"
    smoke = {(tests / name).resolve() for name in SMOKE_FILES}
    for item in items:
        if Path(str(item.fspath)).resolve() in smoke and item.get_closest_marker("slow") is None:
            item.add_marker(pytest.mark.smoke)


@pytest.hookimpl(trylast=True)
def pytest_runtest_teardown(item, nextitem):
    if _SIGINTS:
        item.session.shouldstop = "interrupted (Ctrl-C)"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Root of the real data samples; tests that need them skip with the reason where absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data samples not found at {SHARED_DATA} (the ../shared checkout is absent)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def wxbs_root(shared_data) -> Path:
    """The WxBS v1.1 release as its zip unpacks (the folder holding v1.1/)."""
    root = shared_data / "WxBS"
    if not (root / "v1.1").is_dir():
        pytest.skip(f"WxBS v1.1 not found at {root} (the ../shared data lacks it)")
    return root


@pytest.fixture(scope="session")
def evd_root(shared_data) -> Path:
    """The EVD release as its zip unpacks (1/, 2/, h/)."""
    root = shared_data / "EVD"
    if not (root / "h").is_dir():
        pytest.skip(f"EVD not found at {root} (the ../shared data lacks it)")
    return root
