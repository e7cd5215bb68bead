"""The matcher registry: built-ins and plugins through one `register`, the example
plugin found by its entry point, --matcher module:factory, and broken matchers."""

from __future__ import annotations

import ast
import dataclasses
import importlib
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from e3cm_bench.storage.cache import MatchCache
from e3cm_bench.matchers.plugin_code import code_sha256
from e3cm_bench.matchers import MatcherEntry, get_matcher, matcher_names, register, registry, unregister
from e3cm_bench.ground.matches import Matches
from e3cm_bench.method.spec import MethodSpec
from e3cm_bench.pipeline.runner import run_benchmark
from helpers import flat, invoke, one_line_error

REPO = Path(__file__).resolve().parents[2]
PACKAGE = REPO / "e3cm_bench"
PLUGIN_SRC = REPO / "examples" / "plugin" / "src"
BUILTINS = ("e3cm", "e3cm-ransac", "e3cm-release", "e3cm-plus", "direct", "dfm", "sift", "colmap-sift")
PEERS = ("loftr", "superpoint+superglue", "superpoint+lightglue", "disk+lightglue", "aliked+lightglue")


# --------------------------------------------------------------------------- the registry


def test_builtins_are_registered_entries_with_settings_and_origin():
    assert matcher_names()[:len(BUILTINS + PEERS)] == list(BUILTINS + PEERS)
    for name in BUILTINS + PEERS:
        entry = get_matcher(name)
        assert isinstance(entry, MatcherEntry) and entry.origin == "built-in" and entry.description
    assert get_matcher("sift").needs_backbone is False and get_matcher("dfm").needs_backbone is True
    # a preset is its matcher with fixed settings: same identity as e3cm --estimator ransac
    preset = MethodSpec.create("e3cm-ransac", seed=3)
    assert preset == MethodSpec.create("e3cm", estimator="ransac", seed=3)
    assert preset.label == "e3cm-ransac" and preset.seed == 3
    assert MethodSpec.create("e3cm").seed is None and MethodSpec.create("dfm").seed == 0  # is_random by settings
    assert MethodSpec.create("e3cm-release", options={"cascade": False}).seed is None


def test_settings_are_checked_against_the_entry_in_one_line():
    with pytest.raises(ValueError, match=r"^e3cm: unknown setting\(s\) bogus; it takes: .*num_levels"):
        MethodSpec.create("e3cm", options={"bogus": 1})
    with pytest.raises(ValueError, match="ratio must be in"):
        MethodSpec.create("sift", options={"ratio": 1.5})
    with pytest.raises(ValueError, match="e3cm-ransac is e3cm with estimator=ransac"):
        MethodSpec.create("e3cm-ransac", estimator="top8")
    with pytest.raises(ValueError, match="direct is e3cm without the cascade"):
        MethodSpec.create("direct", options={"cascade": True})
    with pytest.raises(ValueError, match="num_levels must be a whole number 2..5"):
        MethodSpec.create("dfm", options={"num_levels": 7})
    with pytest.raises(ValueError, match="unknown matcher 'nope'; choose one of: e3cm, "):
        MethodSpec.create("nope")
    # sift now takes its own settings; given ones enter the identity
    assert MethodSpec.create("sift", options={"cross_check": True}).identity()["settings"] == {"cross_check": True}


def test_a_matcher_registered_in_a_test_shows_in_the_listing():
    entry = register(MatcherEntry("test-grid", "a matcher registered by a test", build=lambda s: None,
                                  origin="test"))
    try:
        result = invoke("matchers")
        assert result.exit_code == 0
        text = result.output
        assert "test-grid (test) a matcher registered by a test" in flat(text)  # wrapped at 80 columns
        for name in BUILTINS:
            assert f"\n{name}  (built-in)" in "\n" + text
        assert "cascade=true, estimator=top8" in flat(text) and "max_keypoints=8000, ratio=0.8, cross_check=false" in flat(text)
        assert "= e3cm with estimator=ransac" in flat(text) and "num_levels=5, channel_order=rgb, precision=fp32" in flat(text)
        assert max(len(line) for line in text.splitlines()) <= 80
        with pytest.raises(ValueError, match="already registered"):
            register(dataclasses.replace(entry, description="another"))
    finally:
        unregister(entry.name)


def _string_constants_compared(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, constant) of every comparison / membership test of a name against string constants."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Compare):
            for value in [node.left, *node.comparators]:
                items = value.elts if isinstance(value, (ast.Tuple, ast.List, ast.Set)) else [value]
                found += [(node.lineno, v.value) for v in items if isinstance(v, ast.Constant) and isinstance(v.value, str)]
    return found


def test_no_matcher_name_is_dispatched_on_outside_its_entry():
    """No `x == "dfm"` / `x in ("e3cm", ...)` on a matcher's name anywhere in the package or
    its scripts: what a matcher is lives in its registry entry (matchers/builtin.py)."""
    branches = []
    for path in [*PACKAGE.rglob("*.py"), *(REPO / "scripts").rglob("*.py")]:
        if path.name == "builtin.py":
            continue
        for line, value in _string_constants_compared(ast.parse(path.read_text())):
            if value in BUILTINS + PEERS:
                branches.append(f"{path.relative_to(REPO)}:{line}: {value!r}")
    assert branches == []


# --------------------------------------------------------------------------- plugins


@pytest.fixture
def hpatches_boat(shared_data) -> list:
    return ["--root", shared_data / "hpatches-sequences-release", "--sequences", "v_boat"]


def _example_plugin(tmp_path: Path, monkeypatch, version: str = "0.1.0") -> Path:
    """The example plugin made importable through its metadata, as pip's install would make it:
    a dist-info with its entry point, first on sys.path (before an installed copy)."""
    site = tmp_path / "site"
    info = site / "e3cm_bench_orb-0.1.0.dist-info"
    info.mkdir(parents=True, exist_ok=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: e3cm-bench-orb\nVersion: {version}\n")
    # the entry point exactly as examples/plugin/pyproject.toml declares it
    declared = [line for line in (REPO / "examples/plugin/pyproject.toml").read_text().splitlines()
                if line.startswith("orb = ")]
    (info / "entry_points.txt").write_text("[e3cm_bench.matchers]\n" + declared[0].replace('"', "") + "\n")
    monkeypatch.syspath_prepend(str(PLUGIN_SRC))
    monkeypatch.syspath_prepend(str(site))
    importlib.invalidate_caches()
    registry.load_plugins()
    return info


@pytest.fixture
def example_plugin(tmp_path, monkeypatch):
    info = _example_plugin(tmp_path, monkeypatch)
    yield info
    unregister("orb")


def test_the_example_plugin_is_found_by_entry_point_and_runs_hpatches(example_plugin, hpatches_boat, tmp_path):
    entry = get_matcher("orb")
    code = code_sha256("e3cm_bench_orb")  # every .py file of the package: its identity is its code
    assert entry.origin == "plugin e3cm-bench-orb 0.1.0"
    assert entry.source == {"package": "e3cm-bench-orb", "version": "0.1.0", "sha256": code}
    listing = invoke("matchers", "orb").output
    assert "orb  (plugin e3cm-bench-orb 0.1.0)" in listing and "max_keypoints=5000, scale_factor=1.2" in flat(listing)
    out = tmp_path / "orb"
    result = invoke("hpatches", *hpatches_boat, "--out", out, "--matcher", "orb", "--set", "max_keypoints=1500")
    assert result.exit_code == 0
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["identity"]["matcher"] == "orb" and config["method"] == "orb"
    assert config["identity"]["plugin"] == {"package": "e3cm-bench-orb", "version": "0.1.0", "sha256": code}
    assert config["identity"]["settings"] == {"max_keypoints": 1500}
    # its settings recorded as the built-ins' are, every default in
    assert config["matcher"] == {"matcher": "orb", "max_keypoints": 1500, "scale_factor": 1.2, "n_levels": 8,
                                 "fast_threshold": 20}
    summary = (out / "summary.csv").read_text().splitlines()
    row = dict(zip(summary[0].split(","), summary[1].split(",")))
    assert int(row["n_pairs"]) == 5 and float(row["n_matches"]) > 100
    # ORB + mutual NN on v_boat (zoom + rotation) gets some homographies right at 5 px
    assert float(row["h_acc@5"]) > 0


def test_a_plugin_upgrade_refuses_to_resume_in_one_line(tmp_path, monkeypatch, hpatches_boat):
    info = _example_plugin(tmp_path, monkeypatch)
    try:
        out = tmp_path / "orb"
        assert invoke("hpatches", *hpatches_boat, "--out", out, "--matcher", "orb", "--limit", 1).exit_code == 0
        (info / "METADATA").write_text("Metadata-Version: 2.1\nName: e3cm-bench-orb\nVersion: 0.2.0\n")
        registry.load_plugins()
        assert get_matcher("orb").origin == "plugin e3cm-bench-orb 0.2.0"
        line = one_line_error(invoke("hpatches", *hpatches_boat, "--out", out, "--matcher", "orb", "--limit", 1))
        assert "other settings (plugin.version 0.1.0 -> 0.2.0)" in line and "--overwrite" in line
    finally:
        unregister("orb")


def test_a_plugin_that_fails_to_load_breaks_only_itself(tmp_path, monkeypatch):
    site = tmp_path / "site"
    info = site / "broken_plugin-1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: broken-plugin\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[e3cm_bench.matchers]\nbroken = no_such_module_here:ENTRY\n")
    monkeypatch.syspath_prepend(str(site))
    importlib.invalidate_caches()
    registry.load_plugins()
    try:
        listing = invoke("matchers")
        assert listing.exit_code == 0 and "sift  (built-in)" in listing.output
        assert "broken (not loaded) plugin no_such_module_here:ENTRY (broken-plugin 1.0) failed to load" in flat(listing.output)
        line = one_line_error(invoke("match", "--matcher", "broken"))
        assert "broken-plugin 1.0" in line and "ModuleNotFoundError" in line
    finally:
        registry._BROKEN.pop("broken", None)


MODULE = '''
import numpy as np
from e3cm_bench import Matcher, Matches
import cv2


class Corners(Matcher):
    """Shi-Tomasi corners matched by mutual nearest neighbour of 7x7 grey patches."""
    name = "corners"
    def match(self, image0, image1):
        p0, d0 = self._describe(image0)
        p1, d1 = self._describe(image1)
        pairs = cv2.BFMatcher(cv2.NORM_L2, crossCheck=True).match(d0, d1)
        i0 = np.array([m.queryIdx for m in pairs], int)
        i1 = np.array([m.trainIdx for m in pairs], int)
        return Matches(p0[i0], p1[i1], np.array([-m.distance for m in pairs]))
    def _describe(self, image):
        grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        points = cv2.goodFeaturesToTrack(grey, 300, 0.01, 5).reshape(-1, 2)
        padded = np.pad(grey.astype(np.float32), 3, mode="edge")
        xy = np.round(points).astype(int)
        patches = np.stack([padded[y:y + 7, x:x + 7].ravel() for x, y in xy])
        patches = (patches - patches.mean(1, keepdims=True)) / (patches.std(1, keepdims=True) + 1e-6)
        return points.astype(np.float32), patches.astype(np.float32)


def build():
    return Corners()
'''


def test_a_module_factory_runs_and_its_file_hash_is_its_identity(tmp_path, monkeypatch, hpatches_boat):
    (tmp_path / "mods").mkdir()
    module = tmp_path / "mods" / "my_corners.py"
    module.write_text(MODULE)
    monkeypatch.syspath_prepend(str(tmp_path / "mods"))
    out = tmp_path / "corners"
    try:
        result = invoke("hpatches", *hpatches_boat, "--out", out, "--matcher", "my_corners:build", "--limit", 2)
        assert result.exit_code == 0
        config = yaml.safe_load((out / "config.yaml").read_text())
        assert config["identity"]["matcher"] == "my_corners:build" and config["method"] == "build"
        assert config["identity"]["plugin"]["module"] == "my_corners"
        assert len(config["identity"]["plugin"]["sha256"]) == 64
        assert (out / "summary.csv").is_file()
        # the module changes: a new process (here: a fresh registry entry) refuses to resume
        module.write_text(MODULE + "\n# tuned\n")
        unregister("my_corners:build")
        line = one_line_error(invoke("hpatches", *hpatches_boat, "--out", out, "--matcher", "my_corners:build",
                                     "--limit", 2))
        # both hashes, each by its first 12 digits: the code the folder's matches came from, and this one
        old, new = config["identity"]["plugin"]["sha256"], code_sha256("my_corners")
        assert f"other settings (plugin code: sha256 {old[:12]}... -> {new[:12]}...)" in line, line
        line = one_line_error(invoke("hpatches", *hpatches_boat, "--out", tmp_path / "x", "--matcher", "my_corners:nothing"))
        assert line.endswith("--matcher my_corners:nothing: module my_corners has no 'nothing'")
    finally:
        unregister("my_corners:build")
        sys.modules.pop("my_corners", None)


# --------------------------------------------------------------------------- broken matchers


class Breaks:
    """Sound matches for the first two pairs, then the broken kind."""

    keypoints_in_image = True

    def __init__(self, kind: str):
        self.kind, self.calls, self.name = kind, 0, f"broken-{kind}"

    def match(self, image0, image1):
        self.calls += 1
        k = np.array([[10.0, 10.0], [20.0, 30.0], [40.0, 15.0], [25.0, 25.0]])
        if self.calls <= 2:
            return Matches(k, k + 1, np.ones(4))
        if self.kind == "raises":
            raise KeyError("the model lost its weights")
        if self.kind == "wrong-type":
            return {"keypoints0": k, "keypoints1": k}
        if self.kind == "nan":
            bad = k.copy()
            bad[1, 0] = np.nan
            return Matches(k, bad, np.ones(4))
        if self.kind == "outside":
            return Matches(k, k + [image1.shape[1], 0], np.ones(4))
        m = Matches(k, k, np.ones(4))
        m.keypoints1 = k[:3]  # mismatched lengths, set behind the constructor's back
        return m


@pytest.mark.parametrize("kind, says", [
    ("raises", "raised KeyError: 'the model lost its weights'"),
    ("wrong-type", "returned dict, expected e3cm_bench.Matches"),
    ("nan", "returned bad matches: keypoints1: 1 point(s) not finite"),
    ("outside", "returned bad matches: keypoints1: 4 point(s) outside the"),
    ("lengths", "returned bad matches: keypoints0 has 4 points, keypoints1 3"),
])
def test_a_broken_matcher_gives_one_line_and_keeps_the_cached_pairs(kind, says, tmp_path, hpatches_boat):
    name = f"broken-{kind}"
    register(MatcherEntry(name, "breaks on the third pair", build=lambda s: Breaks(kind), origin="test"))
    try:
        out = tmp_path / name
        line = one_line_error(invoke("hpatches", *hpatches_boat, "--out", out, "--matcher", name))
        assert line.startswith("error: pair v_boat/1-4: matcher ") and says in line
        assert "the pairs matched before it are kept" in line
        assert sorted(MatchCache(out / "matches.h5").names()) == ["v_boat/1-2", "v_boat/1-3"]
    finally:
        unregister(name)


def test_the_api_takes_a_registered_matcher(tmp_path, shared_data):
    register(MatcherEntry("api-sift-strict", "sift with cross check, by the API",
                          build=lambda s: get_matcher("sift").build(get_matcher("sift").make_settings({"cross_check": True})),
                          origin="test"))
    try:
        method = MethodSpec.create("api-sift-strict", max_side=320)
        summary = run_benchmark("hpatches", tmp_path / "run", method, root=shared_data / "hpatches-sequences-release",
                                dataset_options={"sequences": ["v_boat"]}, limit=2)
        assert summary.iloc[0]["n_pairs"] == 2 and method.label == "api-sift-strict"
    finally:
        unregister("api-sift-strict")


def test_the_registry_is_documented_as_the_way_in():
    text = (REPO / "docs" / "own-matcher.md").read_text()
    assert "## Benchmark your own matcher" in text
    for needle in ('[project.entry-points."e3cm_bench.matchers"]', "--matcher my_package.module:factory",
                   "e3cm-bench import hpatches", "e3cm-bench check"):
        assert needle in text, needle
