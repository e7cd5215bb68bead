"""Shared fixtures: the real benchmark samples in ../shared/data (skip cleanly without them)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

# The test modules sit in subfolders by subject; helpers.py, http_server.py and slurm_cluster.py
# sit here, in tests/, and are imported by name from every subfolder, whatever the import mode.
TESTS = Path(__file__).resolve().parent
if str(TESTS) not in sys.path:
    sys.path.insert(0, str(TESTS))

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"


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
