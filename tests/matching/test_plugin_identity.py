"""A plugin's identity is its code: a plugin edited between two runs (as an editable install
is, keeping its name and version) is a new identity, so the rerun into the same folder is
refused, or rematched with --overwrite, and never scores the old code's matches as the new's.
Its settings are recorded as the built-ins' are: settings(), else what it was built from."""

from __future__ import annotations

import importlib
import sys
import textwrap
from pathlib import Path

import pandas as pd
import pytest
import yaml

from e3cm_bench.ground.files import file_sha256
from e3cm_bench.matchers import get_matcher, registry, unregister
from e3cm_bench.matchers.plugin_code import bound_defaults, code_sha256
from helpers import invoke, one_line_error

MATCHER = '''
import cv2
import numpy as np
from e3cm_bench import Matcher, Matches

from .util import grey


class RatioSift(Matcher):
    """SIFT with Lowe's ratio test: the ratio is what the edits below change."""
    name = "ratio-sift"

    def __init__(self, ratio):
        self.ratio = ratio
        self.sift = cv2.SIFT_create(500)

    def match(self, image0, image1):
        k0, d0 = self.sift.detectAndCompute(grey(image0), None)
        k1, d1 = self.sift.detectAndCompute(grey(image1), None)
        pairs = [m for m, n in cv2.BFMatcher().knnMatch(d0, d1, k=2) if m.distance < self.ratio * n.distance]
        x0 = np.float32([k0[m.queryIdx].pt for m in pairs]).reshape(-1, 2)
        x1 = np.float32([k1[m.trainIdx].pt for m in pairs]).reshape(-1, 2)
        return Matches(x0, x1, np.float32([-m.distance for m in pairs]))
'''
UTIL = "import cv2\n\n\ndef grey(image):\n    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)\n"


def write_package(folder: Path, name: str, tail: str) -> Path:
    """A package NAME in `folder`: the matcher module, a helper module, and `tail` in __init__."""
    package = folder / name
    package.mkdir(parents=True, exist_ok=True)
    (package / "matcher.py").write_text(MATCHER)
    (package / "util.py").write_text(UTIL)
    (package / "__init__.py").write_text(textwrap.dedent(tail))
    return package


def forget(name: str) -> None:
    """The package's modules out of sys.modules: the next import reads the edited files, as the
    next command (a new process) would."""
    for module in [m for m in sys.modules if m == name or m.startswith(name + ".")]:
        del sys.modules[module]
    importlib.invalidate_caches()


def config_of(out: Path) -> dict:
    return yaml.safe_load((out / "config.yaml").read_text())


def n_matches(out: Path) -> float:
    return float(pd.read_csv(out / "summary.csv")["n_matches"].iloc[0])


@pytest.fixture
def boat(shared_data) -> list:
    return ["--root", shared_data / "hpatches-sequences-release", "--sequences", "v_boat", "--limit", 1,
            "--max-side", 480]


def test_a_module_factory_edited_in_its_package_is_refused_then_rematched(tmp_path, monkeypatch, boat):
    """--matcher pkg.module:factory: the factory's defaults are the recorded settings, and an edit
    of any .py file of its package (here its helper, not the module named) is a new identity."""
    package = write_package(tmp_path / "mods", "ratiomod", "")
    (package / "factory.py").write_text("from .matcher import RatioSift\n\n\ndef build(ratio=0.8):\n"
                                        "    return RatioSift(ratio)\n")
    monkeypatch.syspath_prepend(str(tmp_path / "mods"))
    out, name = tmp_path / "run", "ratiomod.factory:build"
    try:
        assert invoke("hpatches", *boat, "--out", out, "--matcher", name).exit_code == 0
        first, matched_first = config_of(out), n_matches(out)
        assert first["matcher"] == {"matcher": "ratio-sift", "ratio": 0.8}
        assert first["identity"]["plugin"]["module"] == "ratiomod.factory"
        assert first["identity"]["plugin"]["sha256"] == code_sha256("ratiomod")
        # the same code: resumes (evaluating only)
        assert "evaluating only" in invoke("hpatches", *boat, "--out", out, "--matcher", name).output
        (package / "util.py").write_text(UTIL + "\n# tuned\n")
        forget("ratiomod")
        unregister(name)
        line = one_line_error(invoke("hpatches", *boat, "--out", out, "--matcher", name))
        assert "other settings" in line and "--overwrite" in line
        # the changed code named with both values (each hash's first 12 digits)
        old, new = first["identity"]["plugin"]["sha256"], code_sha256("ratiomod")
        assert f"plugin code: sha256 {old[:12]}... -> {new[:12]}..." in line, line
        (package / "factory.py").write_text((package / "factory.py").read_text().replace("0.8", "0.6"))
        forget("ratiomod")
        unregister(name)
        result = invoke("hpatches", *boat, "--out", out, "--matcher", name, "--overwrite")
        assert result.exit_code == 0 and "evaluating only" not in result.output
        second = config_of(out)
        assert second["matcher"]["ratio"] == 0.6
        assert second["identity"]["plugin"]["sha256"] not in (None, first["identity"]["plugin"]["sha256"])
        # the matches are the new code's: a stricter ratio keeps fewer
        assert 0 < n_matches(out) < matched_first
    finally:
        unregister(name)
        forget("ratiomod")


ENTRY_INIT = '''
from dataclasses import dataclass

from e3cm_bench import MatcherEntry

from .matcher import RatioSift


@dataclass(frozen=True)
class Settings:
    ratio: float = 0.8


ENTRY = MatcherEntry(name="ratio-plugin", description="SIFT + ratio, a plugin edited between runs",
                     build=lambda settings: RatioSift(settings.ratio), settings=Settings)
'''


def install_editable(tmp_path: Path, monkeypatch) -> Path:
    """The package installed as `pip install -e` leaves it: its source folder on the path and a
    dist-info naming its entry point, with a version that no edit changes."""
    source, site = tmp_path / "src", tmp_path / "site"
    package = write_package(source, "ratio_plugin", ENTRY_INIT)
    info = site / "ratio_plugin-1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: ratio-plugin\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[e3cm_bench.matchers]\nratio-plugin = ratio_plugin:ENTRY\n")
    monkeypatch.syspath_prepend(str(source))
    monkeypatch.syspath_prepend(str(site))
    importlib.invalidate_caches()
    registry.load_plugins()
    return package


def test_an_editable_plugin_changed_between_two_runs_is_never_scored_stale(tmp_path, monkeypatch, boat):
    package = install_editable(tmp_path, monkeypatch)
    out = tmp_path / "run"
    try:
        entry = get_matcher("ratio-plugin")
        assert entry.source["package"] == "ratio-plugin" and entry.source["version"] == "1.0"
        assert entry.source["sha256"] == code_sha256("ratio_plugin")
        assert invoke("hpatches", *boat, "--out", out, "--matcher", "ratio-plugin").exit_code == 0
        before = config_of(out)
        assert before["matcher"] == {"matcher": "ratio-sift", "ratio": 0.8}  # the settings dataclass, defaults in
        # the edit a researcher makes: the ratio's default; the version stays 1.0
        (package / "__init__.py").write_text(ENTRY_INIT.replace("ratio: float = 0.8", "ratio: float = 0.7"))
        forget("ratio_plugin")
        registry.load_plugins()  # what the next command finds
        assert get_matcher("ratio-plugin").source["version"] == "1.0"
        line = one_line_error(invoke("hpatches", *boat, "--out", out, "--matcher", "ratio-plugin"))
        assert "made with other settings" in line, line
        old, new = before["identity"]["plugin"]["sha256"], code_sha256("ratio_plugin")
        assert f"plugin code: sha256 {old[:12]}... -> {new[:12]}..." in line, line
        assert config_of(out)["matcher"]["ratio"] == 0.8  # the refusal left the record alone
        result = invoke("hpatches", *boat, "--out", out, "--matcher", "ratio-plugin", "--overwrite")
        assert result.exit_code == 0 and "evaluating only" not in result.output
        after = config_of(out)
        assert after["matcher"]["ratio"] == 0.7
        assert after["identity"]["plugin"]["sha256"] != before["identity"]["plugin"]["sha256"]
    finally:
        unregister("ratio-plugin")
        forget("ratio_plugin")


def test_settings_hook_and_defaults_are_what_config_records(tmp_path, monkeypatch, boat):
    """settings() is recorded as the matcher gives it; a module outside a package keeps the hash
    of its one file (so folders written before keep resuming)."""
    (tmp_path / "mods").mkdir()
    module = tmp_path / "mods" / "hooked.py"
    module.write_text("import numpy as np\nfrom e3cm_bench import Matcher, Matches\n\n\n"
                      "class Hooked(Matcher):\n    name = 'hooked'\n\n"
                      "    def settings(self):\n        return {'window': 7, 'mode': 'fast'}\n\n"
                      "    def match(self, image0, image1):\n        x = np.float32([[10, 10], [20, 30], [40, 50]])\n"
                      "        return Matches(x, x, np.ones(3))\n\n\n"
                      "def build(scale=2.0, names=('a', 'b')):\n    return Hooked()\n")
    monkeypatch.syspath_prepend(str(tmp_path / "mods"))
    out = tmp_path / "run"
    try:
        assert invoke("hpatches", *boat, "--out", out, "--matcher", "hooked:build").exit_code == 0
        config = config_of(out)
        assert config["matcher"] == {"matcher": "hooked", "window": 7, "mode": "fast"}
        assert config["identity"]["plugin"]["sha256"] == file_sha256(module)
        import hooked

        assert bound_defaults(hooked.build) == {"scale": 2.0, "names": ["a", "b"]}
    finally:
        unregister("hooked:build")
        forget("hooked")
