"""The package's structure, read from its source (ast): one owner for the run folder's file
names, and no import cycles (docs/architecture.md)."""

from __future__ import annotations

import ast
import re
import importlib.util
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "e3cm_bench"
OWNER = PACKAGE / "run" / "folder.py"
RUN_FILES = ("matches.h5", "config.yaml", "per_pair.csv", "summary.csv", "skipped.csv", "failures.csv", ".feature-spill")


def code_shape():
    """scripts/code_shape.py, the one reader of the import graph (the layer table uses it too)."""
    if "code_shape" not in sys.modules:
        script = min((REPO / "scripts").rglob("code_shape.py"))  # scripts/ or a folder of it
        spec = importlib.util.spec_from_file_location("code_shape", script)
        module = importlib.util.module_from_spec(spec)
        sys.modules["code_shape"] = module  # dataclasses look their module up while it loads
        spec.loader.exec_module(module)
    return sys.modules["code_shape"]


def _docstrings(tree: ast.Module) -> set[int]:
    kinds = (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)
    return {id(node.body[0].value) for node in ast.walk(tree)
            if isinstance(node, kinds) and node.body and isinstance(node.body[0], ast.Expr)
            and isinstance(node.body[0].value, ast.Constant)}


def run_file_names(path: Path, root: Path = REPO) -> tuple[list[str], list[str]]:
    """Where a module names a run folder's file: (as a path, in prose), each 'file:line: text'.

    A string that is the file's name, or a path ending in it or going through it
    (``"matches.h5"``, ``f"{out}/summary.csv"``), builds a path into a run folder: only the
    owner may. A sentence that mentions one (a help text, an error message) describes the
    layout to a reader; those are listed, not failed."""
    tree = ast.parse(path.read_text(), str(path))
    skip = _docstrings(tree)
    where = path.relative_to(root)
    as_path, in_prose = [], []
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Constant) and isinstance(node.value, str)) or id(node) in skip:
            continue
        text = node.value.strip()
        for name in RUN_FILES:
            if name not in text:
                continue
            pathlike = text == name or text.endswith("/" + name) or text.startswith(name + "/") or f"/{name}/" in text
            (as_path if pathlike else in_prose).append(f"{where}:{node.lineno}: {name} in {node.value[:80]!r}")
    return as_path, in_prose


def test_the_scan_finds_a_run_file_name_built_into_a_path(tmp_path):
    module = tmp_path / "e3cm_bench" / "bad.py"
    module.parent.mkdir()
    module.write_text('"""Names config.yaml in its docstring: fine."""\n'
                      'from pathlib import Path\n'
                      'def f(out):\n'
                      '    return Path(out) / "matches.h5", f"{out}/summary.csv"\n'
                      'HELP = "Run folder (config.yaml, CSVs)."\n')
    as_path, in_prose = run_file_names(module, root=tmp_path)
    assert [line.split(": ")[0:2] for line in as_path] == [["e3cm_bench/bad.py:4", "matches.h5 in 'matches.h5'"],
                                                           ["e3cm_bench/bad.py:4", "summary.csv in '/summary.csv'"]]
    assert len(in_prose) == 1 and in_prose[0].startswith("e3cm_bench/bad.py:5: config.yaml")


# interchange's hloc format writes hloc's own files, features.h5 and matches.h5: the same name as
# the run folder's match cache, another tool's file in another folder. Exempt by file and name only.
FOREIGN = {("e3cm_bench/interchange/export.py", "matches.h5"), ("e3cm_bench/interchange/hloc.py", "matches.h5")}


def _exempt(line: str) -> bool:
    where, rest = line.split(":", 1)[0], line.split(": ", 1)[1]
    return (where, rest.split(" in ")[0]) in FOREIGN


def test_only_the_run_folder_names_its_files():
    """Every module but run/folder.py asks RunFolder for a run folder's paths."""
    as_path, in_prose = [], []
    for path in sorted(PACKAGE.rglob("*.py")):
        if path != OWNER:
            found = run_file_names(path)
            as_path += [line for line in found[0] if not _exempt(line)]
            in_prose += found[1]
    if in_prose:
        print("run-folder files mentioned in messages and help (not failed):", *in_prose, sep="\n  ")
    assert not as_path, "run-folder file names outside e3cm_bench/run/folder.py:\n" + "\n".join(as_path)


def test_the_owner_names_them():
    """The scan would see the names where they belong (so an empty result elsewhere means something)."""
    as_path, _ = run_file_names(OWNER)
    assert {line.split(": ")[1].split(" in ")[0] for line in as_path} == set(RUN_FILES)


def test_no_import_cycles():
    """No module imports itself through others at import time (module-level imports)."""
    shape = code_shape()
    cycles = shape.cycles(shape.import_graph())
    assert not cycles, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_the_cycle_finder_finds_one():
    shape = code_shape()
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert shape.cycles(graph) == [["a", "b", "c"]]
    with pytest.raises(ValueError, match="import cycle"):
        shape.layers(graph)
    assert shape.layers({"a": {"b"}, "b": set(), "c": {"a", "b"}}) == {"a": 1, "b": 0, "c": 2}


def test_the_import_graph_reads_relative_and_lazy_imports():
    """Edges as Python resolves them: `from . import x` is the submodule x, `from .x import y`
    the module x, a function's import only with module_level=False."""
    shape = code_shape()
    eager, every = shape.import_graph(), shape.import_graph(module_level=False)
    assert "e3cm_bench.run" in eager["e3cm_bench.runner"]  # from .run import RunFolder: the package
    assert "e3cm_bench.run.folder" in eager["e3cm_bench.run"]
    assert "e3cm_bench.metrics" in eager["e3cm_bench.benchmarks.base"]  # from .. import metrics
    assert "e3cm_bench.method" not in eager["e3cm_bench.benchmarks.base"]  # imported in resolve_method
    assert "e3cm_bench.method" in every["e3cm_bench.benchmarks.base"]


def test_every_path_docs_architecture_names_exists():
    """docs/architecture.md names modules by path (relative to e3cm_bench/, or to the
    repository): a move that leaves the page behind fails here."""
    text = (REPO / "docs" / "architecture.md").read_text()
    paths = set(re.findall(r"`([\w./]+(?:\.py|/))`", text))
    assert len(paths) > 30
    missing = sorted(p for p in paths if not (PACKAGE / p).exists() and not (REPO / p).exists())
    assert not missing, f"docs/architecture.md names paths that do not exist: {', '.join(missing)}"
