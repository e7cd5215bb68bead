"""The interchange formats' registry: each format declared once, in its own module, with its
reader, writer, pixel origin and help; `import`'s options, `export --to`'s choices and the
--pixel-origin help come from it, so that a format declared in one module outside the package
gets both commands (a toy format round-trips a run to the same per_pair.csv)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace

import pytest

from e3cm_bench.interchange import registry
from e3cm_bench.interchange.registry import Format, formats, get_format, origin_help, register, source_label
from helpers import invoke, one_line_error

REPO_ROOT = Path(__file__).resolve().parents[2]

# A format that is none of the built-in ones: one JSON file, {pair name: [[x0, y0, x1, y1, score], ...]}
# in the corner convention, declared in this one module and nowhere else.
TOY_FORMAT = '''
import json
from pathlib import Path

import numpy as np

from e3cm_bench.ground.files import file_sha256
from e3cm_bench.interchange import MissingPair, from_origin, to_origin
from e3cm_bench.interchange.registry import Format, register
from e3cm_bench.ground.matches import Matches


@register
class ToyFormat(Format):
    name = "toy"
    origin = "corner"
    reads = ("TOY.json",)
    import_help = "A toy file of matches (one JSON object)."
    writes = "toy.json"
    outputs = ("toy.json",)
    labelled_by = "path"

    def source(self, paths, benchmark, origin=None):
        return ToySource(*paths, origin=origin)

    def write(self, out, items, origin, job):
        rows = {item.name: np.column_stack([to_origin(item.matches.keypoints0, origin),
                                            to_origin(item.matches.keypoints1, origin),
                                            item.matches.scores.astype(np.float64)]).tolist() for item in items}
        path = out / "toy.json"
        path.write_text(json.dumps(rows))
        return [path]


class ToySource:
    format = "toy"
    per_pair = False

    def __init__(self, path, origin=None):
        self.path, self.origin = Path(path), origin or ToyFormat.origin
        self.rows = json.loads(self.path.read_text())

    def files(self, pairs):
        return {"toy": file_sha256(self.path)}

    def identity(self, files):
        return {"format": self.format, "files": files}

    def location(self):
        return {"toy": str(self.path), "pixel_origin": self.origin}

    def expected(self, pair, root):
        return f"{self.path}: key {pair.name}"

    def read(self, pair, root):
        if pair.name not in self.rows:
            raise MissingPair(f"no {pair.name} in {self.path}")
        rows = np.asarray(self.rows[pair.name], np.float64).reshape(-1, 5)
        return Matches(from_origin(rows[:, 0:2], self.origin), from_origin(rows[:, 2:4], self.origin), rows[:, 4])
'''


def test_each_built_in_format_is_declared_once_in_its_own_module():
    found = formats()
    assert list(found) == ["colmap", "gluefactory", "hloc", "npz"]
    for name, fmt in found.items():
        assert type(fmt).__module__ == f"e3cm_bench.interchange.{name}"
        assert fmt.name == name and fmt.origin in ("center", "corner") and fmt.reads and fmt.import_help and fmt.writes
    assert {n: f.origin for n, f in found.items()} == {"colmap": "corner", "gluefactory": "corner", "hloc": "center",
                                                      "npz": "center"}
    assert [n for n, f in found.items() if f.merges] == ["colmap", "hloc"]
    assert [n for n, f in found.items() if f.stores_geometry] == ["colmap"]
    assert origin_help() == "colmap, gluefactory: corner; hloc, npz: center"


def test_a_source_takes_its_formats_own_pixel_origin_by_default(tmp_path):
    from e3cm_bench.interchange import NpzSource

    assert NpzSource(tmp_path).origin == get_format("npz").origin
    assert NpzSource(tmp_path, origin="corner").origin == "corner"
    assert "--pixel-origin must be one of center, corner" in str(pytest.raises(ValueError, NpzSource, tmp_path,
                                                                                  origin="middle").value)


def test_register_refuses_a_name_that_cannot_be_a_flag_and_an_unknown_origin(monkeypatch):
    monkeypatch.setattr(registry, "FORMATS", dict(registry.FORMATS))
    with pytest.raises(ValueError, match="not one"):
        register(type("Bad", (Format,), {"name": "two words"}))
    with pytest.raises(ValueError, match="--pixel-origin must be one of"):
        register(type("Bad", (Format,), {"name": "bad", "origin": "middle"}))
    with pytest.raises(ValueError, match="--pixel-origin must be one of"):  # a format states its own origin
        register(type("Bad", (Format,), {"name": "bad"}))
    assert "bad" not in registry.FORMATS
    with pytest.raises(ValueError, match="--to must be one of colmap, gluefactory, hloc, npz, got 'bad'"):
        get_format("bad")


def test_labels_come_from_the_formats(tmp_path):
    hloc, npz = (SimpleNamespace(format=f) for f in ("hloc", "npz"))
    hloc.matches = tmp_path / "matches-disk-lightglue.h5"
    npz.folder = tmp_path / "my_matches"
    assert source_label(hloc) == "disk-lightglue" and source_label(npz) == "my_matches"
    assert source_label(SimpleNamespace(format="gluefactory", predictions=tmp_path / "exp1" / "predictions.h5")) == "exp1"
    assert source_label(SimpleNamespace(format="elsewhere")) == "imported-elsewhere"


def cli(toy: Path, *args, cwd: Path) -> subprocess.CompletedProcess:
    """e3cm-bench in a fresh interpreter that imported the toy module first (as a plugin would)."""
    code = ("import sys; sys.path.insert(0, sys.argv[1]); import toy_format\n"
            "sys.argv = ['e3cm-bench', *sys.argv[2:]]\nfrom e3cm_bench.__main__ import main\nmain()")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO_ROOT), str(REPO_ROOT / "tests")]), "COLUMNS": "200"}
    return subprocess.run([sys.executable, "-c", code, str(toy), *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, env=env, timeout=600)


def test_a_format_declared_in_one_module_gets_import_and_export(shared_data, tmp_path):
    toy = tmp_path / "plugin"
    toy.mkdir()
    (toy / "toy_format.py").write_text(textwrap.dedent(TOY_FORMAT))
    helps = [cli(toy, command, "--help", cwd=tmp_path) for command in ("import", "export")]
    assert all(h.returncode == 0 for h in helps), [h.stderr for h in helps]
    assert "--toy" in helps[0].stdout and "A toy file of matches" in helps[0].stdout
    assert "toy (toy.json)" in helps[1].stdout and "toy: corner" in helps[1].stdout

    root = shared_data / "hpatches-sequences-release"
    run = tmp_path / "sift"
    select = ["hpatches", "--root", root, "--sequences", "v_boat", "--limit", "3"]
    assert invoke(*select, "--out", run, "--matcher", "sift").exit_code == 0
    exported = cli(toy, "export", run, tmp_path / "out", "--to", "toy", cwd=tmp_path)
    assert exported.returncode == 0, exported.stderr
    said = " ".join(exported.stdout.split())  # wrapped at the terminal's width (80 columns in a pipe)
    assert "-> toy in" in said and "(pixel origin: corner)" in said
    back = tmp_path / "back"
    imported = cli(toy, "import", *select, "--out", back, "--toy", tmp_path / "out" / "toy.json", cwd=tmp_path)
    assert imported.returncode == 0, imported.stderr
    assert (back / "per_pair.csv").read_bytes() == (run / "per_pair.csv").read_bytes()
    # the built-in commands, without the module, know nothing of it
    assert "--to must be one of colmap, gluefactory, hloc, npz" in one_line_error(
        invoke("export", run, tmp_path / "x", "--to", "toy"))
