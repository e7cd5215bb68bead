"""The package's structure, read from its source (ast), as docs/architecture.md states it: one
owner for the run folder's file names, no import cycles (package __init__s included), the size
targets, one home for the default backbone, and every path and object the page names."""

from __future__ import annotations

import ast
import importlib
import importlib.util
import re
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "e3cm_bench"
# The run folder's owners: storage/folder.py (the layout) and storage/run_config.py (config.yaml's record).
OWNERS = (PACKAGE / "storage" / "folder.py", PACKAGE / "storage" / "run_config.py")
RUN_FILES = ("matches.h5", "config.yaml", "per_pair.csv", "summary.csv", "skipped.csv", "failures.csv", ".feature-spill")


def code_shape():
    """scripts/maintain/code_shape.py, the one reader of the import graph (the layer table uses it too)."""
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


# The same names for another tool's file in another folder. Exempt by file and name only:
# - interchange's hloc format writes hloc's own files, features.h5 and matches.h5 (the run
#   folder's match cache has the same name);
# - wxbs_evd_tables.py writes its table of the runs as OUT/summary.csv, a results folder, not a run.
FOREIGN = {("e3cm_bench/pipeline/export.py", "matches.h5"), ("e3cm_bench/interchange/hloc.py", "matches.h5"),
           ("scripts/results/wxbs_evd_tables.py", "summary.csv")}
# Where a run folder's files may be named: the package and the scripts (the scripts read and copy
# runs too); tests build run folders by hand on purpose and are not scanned.
SCANNED = ("e3cm_bench", "scripts")


def _exempt(line: str) -> bool:
    where, rest = line.split(":", 1)[0], line.split(": ", 1)[1]
    return (where, rest.split(" in ")[0]) in FOREIGN


def run_file_uses(root: Path = REPO) -> tuple[list[str], list[str]]:
    """(as a path, in prose) over the modules of SCANNED below `root`, the owners and FOREIGN left out."""
    owners = {owner.relative_to(REPO) for owner in OWNERS}
    as_path, in_prose = [], []
    for path in sorted(p for folder in SCANNED for p in (root / folder).rglob("*.py")):
        if path.relative_to(root) not in owners:
            found = run_file_names(path, root)
            as_path += [line for line in found[0] if not _exempt(line)]
            in_prose += found[1]
    return as_path, in_prose


def test_the_scan_covers_the_scripts(tmp_path):
    """A script that builds a run folder's path fails the scan; the owner's own names do not."""
    for owner in OWNERS:
        (tmp_path / owner.relative_to(REPO)).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / owner.relative_to(REPO)).write_text('CONFIG = "config.yaml"\n')
    script = tmp_path / "scripts" / "results" / "bad.py"
    script.parent.mkdir(parents=True)
    script.write_text('import yaml\ndef read(run):\n    return yaml.safe_load((run / "config.yaml").read_text())\n')
    as_path, _ = run_file_uses(tmp_path)
    assert [line.split(": ")[0:2] for line in as_path] == [["scripts/results/bad.py:3", "config.yaml in 'config.yaml'"]]
    assert (REPO / "scripts" / "results").is_dir()  # the real scan reads the scripts, not an empty folder


def test_only_the_run_folder_names_its_files():
    """Every module and script but the run folder's owners asks RunFolder for a run folder's paths."""
    as_path, in_prose = run_file_uses()
    if in_prose:
        print("run-folder files mentioned in messages and help (not failed):", *in_prose, sep="\n  ")
    assert not as_path, "run-folder file names outside e3cm_bench/storage/folder.py and storage/run_config.py:\n" + "\n".join(as_path)


def test_the_owner_names_them():
    """The scan would see the names where they belong (so an empty result elsewhere means something)."""
    as_path = [line for owner in OWNERS for line in run_file_names(owner)[0]]
    assert {line.split(": ")[1].split(" in ")[0] for line in as_path} == set(RUN_FILES)


def test_no_import_cycles():
    """No module imports itself through others at import time (module-level imports, with the
    package __init__s that importing a submodule runs)."""
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
    assert "e3cm_bench.storage" in eager["e3cm_bench.pipeline.runner"]  # from e3cm_bench.storage import RunFolder: the package
    assert "e3cm_bench.storage.folder" in eager["e3cm_bench.storage"]
    assert "e3cm_bench.geometry.metrics" in eager["e3cm_bench.benchmarks.eval_settings"]  # from e3cm_bench.geometry import metrics
    lazy = {(a, b) for a in every for b in every[a] - eager[a]}  # torch-free start, cycles: imports in functions
    assert len(lazy) > 50 and all(every[a] >= eager[a] for a in eager)


def test_importing_a_submodule_runs_its_packages(tmp_path):
    """`from .a.b.c import x` runs a/__init__ and a/b/__init__ first: edges of the graph, except
    the packages the importer lies in (begun before its first line)."""
    files = {"__init__.py": "", "top.py": "from .a.b.c import x\n", "a/__init__.py": "from .b import c\nfrom . import lazy\n",
             "a/b/__init__.py": "", "a/b/c.py": "x = 1\n", "a/b/d.py": "from . import c\nfrom ..b.c import x\n",
             "a/lazy.py": "def f():\n    from ..top import g\n"}
    for name, text in files.items():
        (tmp_path / "p" / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / "p" / name).write_text(text)
    shape = code_shape()
    graph = shape.import_graph(tmp_path / "p")
    assert graph["p.top"] == {"p.a", "p.a.b", "p.a.b.c"}
    assert graph["p.a.b.d"] == {"p.a.b.c"}  # p.a and p.a.b are begun when d runs
    assert shape.import_graph(tmp_path / "p", packages=False)["p.top"] == {"p.a.b.c"}
    assert graph["p.a.lazy"] == set() and shape.import_graph(tmp_path / "p", module_level=False)["p.a.lazy"] == {"p.top"}
    # a.lazy's function imports top, whose import runs a/__init__: a cycle only a function's import may close
    assert shape.cycles(shape.import_graph(tmp_path / "p", module_level=False)) == [["p.a", "p.a.lazy", "p.top"]]


# The function-level imports that would close an import cycle at their module's top (through a
# package __init__ that the import runs, or two modules reaching each other). Every other
# function-level import only defers a heavy or rarely used import (torch, scipy, matplotlib;
# docs/cli.md "Startup").
CYCLE_CLOSING: set = set()  # none: every import could stand at its module's top
# The function-level imports on a cycle of the graph of every import: modules that reach each
# other only inside functions (at run time, each after the other has loaded), and CYCLE_CLOSING.
IN_CYCLES = CYCLE_CLOSING


def test_function_level_imports_close_exactly_the_listed_cycles():
    """The function-level imports that would make an import cycle at their module's top are
    exactly CYCLE_CLOSING, and those on a cycle of the graph of every import (functions' too,
    with the package __init__s they run) exactly IN_CYCLES (docs/architecture.md, Layers)."""
    shape = code_shape()
    found = shape.cycle_closing()
    assert found == CYCLE_CLOSING, (f"new: {sorted(found - CYCLE_CLOSING)}; listed but closing no cycle "
                                    f"(drop them from CYCLE_CLOSING): {sorted(CYCLE_CLOSING - found)}")
    on_cycles = shape.lazy_cycle_edges()
    assert on_cycles == IN_CYCLES, (f"function-level imports on a new cycle: {sorted(on_cycles - IN_CYCLES)}; "
                                    f"listed but on no cycle (drop them from IN_CYCLES): {sorted(IN_CYCLES - on_cycles)}")


def test_the_cycle_closing_finder_finds_one(tmp_path):
    for name, text in {"__init__.py": "", "low.py": "def f():\n    from . import high\n", "high.py": "from . import low\n",
                       "other.py": "def g():\n    import json\n    from . import low\n"}.items():
        (tmp_path / "p").mkdir(exist_ok=True)
        (tmp_path / "p" / name).write_text(text)
    assert code_shape().cycle_closing(tmp_path / "p") == {("p.low", "p.high")}
    assert code_shape().lazy_cycle_edges(tmp_path / "p") == {("p.low", "p.high")}  # other -> low: on no cycle


def test_no_module_over_the_size_target():
    """The target: no module over 400 lines (scripts/maintain/code_shape.py lists them by size)."""
    shape = code_shape()
    over = sorted((-n, name) for name, n in shape.module_lines().items() if n > shape.MODULE_LINES)
    assert not over, f"modules over {shape.MODULE_LINES} lines:\n" + "\n".join(f"{-n:6d}  {name}" for n, name in over)


def test_no_function_over_the_size_target():
    """The target: no function or method over 60 lines, nested ones included."""
    shape = code_shape()
    long = sorted((-f.lines, f.module, f.name) for f in shape.functions() if f.lines > shape.FUNCTION_LINES)
    assert not long, f"functions over {shape.FUNCTION_LINES} lines:\n" + \
        "\n".join(f"{-n:6d}  {module}.{name}" for n, module, name in long)


def test_the_size_targets_see_what_they_measure(tmp_path):
    """The measures behind the two targets: a module's lines, a function's from `def` to its end."""
    body = "\n".join(f"        x{k} = {k}" for k in range(61))
    (tmp_path / "p").mkdir()
    (tmp_path / "p" / "__init__.py").write_text("")
    (tmp_path / "p" / "m.py").write_text(f"class C:\n    @staticmethod\n    def long():\n{body}\n        \ndef short():\n    pass\n")
    shape = code_shape()
    assert shape.module_lines(tmp_path / "p") == {"p": 0, "p.m": 67}
    assert {(f.name, f.lines) for f in shape.functions(tmp_path / "p")} == {("C.long", 62), ("short", 2)}


# Functions over the parameter target, each with its reason; the test fails when one comes
# under it, so the list cannot go stale.
OVER_EIGHT_PARAMETERS: dict[str, str] = {}  # none (MethodSpec.create takes its options by the option table's names)


def test_no_function_over_eight_parameters():
    """The target (issue 63): no function with more than 8 parameters (positional, keyword-only,
    *args, **kwargs; a method's self or cls not counted): what belongs together travels as one
    frozen dataclass (PoseScoring, LKFit, SetOptions, TimeLimit, ...). Exempt: typer commands,
    those decorated with ``X.command()`` or handed to one (code_shape._typer_commands), because
    typer reads each of their parameters as a command-line option; their count is the command's
    options, and grouping them would hide the options from --help."""
    shape = code_shape()
    every = shape.parameters()
    many = sorted((-f.count, f"{f.module}.{f.name}") for f in every if f.count > shape.PARAMETERS and not f.command)
    unlisted = [(n, name) for n, name in many if name not in OVER_EIGHT_PARAMETERS]
    assert not unlisted, f"functions over {shape.PARAMETERS} parameters:\n" + \
        "\n".join(f"{-n:6d}  {name}" for n, name in unlisted)
    assert set(OVER_EIGHT_PARAMETERS) == {name for _, name in many}, "a listed function is no longer over the target"
    commands = {f"{f.module}.{f.name}" for f in every if f.command}
    assert {"e3cm_bench.cli.match.match", "e3cm_bench.cli.data.import_matches"} <= commands  # decorated; registered
    assert all(name.startswith("e3cm_bench.cli.") for name in commands)


def test_the_parameter_target_sees_what_it_measures(tmp_path):
    """The counter behind the target: every kind of parameter counts, a method's self or cls does
    not (a static method's first does), nested functions are seen, and a typer command is one
    decorated with X.command() or handed, wrapped, to one, in a module that imports typer."""
    (tmp_path / "p").mkdir()
    (tmp_path / "p" / "__init__.py").write_text("")
    (tmp_path / "p" / "m.py").write_text(
        "import typer\napp = typer.Typer()\n"
        "def every(a, /, b, *args, c, d=1, **kw):\n    def inner(x): pass\n"
        "class C:\n    def method(self, a): pass\n    @classmethod\n    def make(cls, a, b): pass\n"
        "    @staticmethod\n    def plain(self, a): pass\n"
        "@app.command()\ndef decorated(a): pass\n"
        "def registered(a): pass\ndef wrap(f): return f\n"
        "app.command('r')(wrap(registered))\n")
    (tmp_path / "p" / "other.py").write_text("class Group:\n    def command(self): pass\n"
                                             "g = Group()\n@g.command()\ndef not_typer(a): pass\n")
    found = {f"{f.module}.{f.name}": (f.count, f.command) for f in code_shape().parameters(tmp_path / "p")}
    assert found == {"p.m.every": (6, False), "p.m.every.inner": (1, False), "p.m.C.method": (1, False),
                     "p.m.C.make": (2, False), "p.m.C.plain": (2, False), "p.m.decorated": (1, True),
                     "p.m.registered": (1, True), "p.m.wrap": (1, False), "p.other.Group.command": (0, False),
                     "p.other.not_typer": (1, False)}


def _string_literals(path: Path) -> list[tuple[int, str]]:
    """(line, text) of every string constant of a module but its docstrings."""
    tree = ast.parse(path.read_text(), str(path))
    skip = _docstrings(tree)
    return [(node.lineno, node.value) for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in skip]


def test_the_default_backbone_is_named_in_the_backbone_modules_only():
    """"vgg19" as a value lives where the backbones are declared; everyone else asks for
    DEFAULT_BACKBONE (a comment or docstring may still mention it)."""
    found = [f"{path.relative_to(REPO)}:{line}: {text[:60]!r}"
             for path in sorted(PACKAGE.rglob("*.py")) if "backbone" not in path.relative_to(PACKAGE).as_posix()
             for line, text in _string_literals(path) if re.search(r"\bvgg19\b", text)]
    assert not found, "the literal 'vgg19' outside the backbone modules:\n" + "\n".join(found)


def test_every_path_docs_architecture_names_exists():
    """docs/architecture.md names modules by path (relative to e3cm_bench/, or to the
    repository): a move that leaves the page behind fails here."""
    text = (REPO / "docs" / "architecture.md").read_text()
    paths = set(re.findall(r"`([\w./]+(?:\.py|/))`", text))
    assert len(paths) > 30
    missing = sorted(p for p in paths if not (PACKAGE / p).exists() and not (REPO / p).exists())
    assert not missing, f"docs/architecture.md names paths that do not exist: {', '.join(missing)}"


def _definitions() -> tuple[set[str], dict[str, set[str]]]:
    """Every name the package defines (classes, functions and methods at any depth, module-level
    assignments) and each class's own attributes (methods, fields, class constants)."""
    names, members = set(), {}
    for path in sorted(PACKAGE.rglob("*.py")):
        tree = ast.parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            if isinstance(node, (ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
                names.add(node.name)
            if isinstance(node, ast.ClassDef):
                own = members.setdefault(node.name, set())
                for item in node.body:
                    if isinstance(item, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                        own.add(item.name)
                    elif isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name):
                        own.add(item.target.id)
                    elif isinstance(item, ast.Assign):
                        own |= {t.id for t in item.targets if isinstance(t, ast.Name)}
        for item in tree.body:
            if isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name):
                names.add(item.target.id)
            elif isinstance(item, ast.Assign):
                names |= {t.id for t in item.targets if isinstance(t, ast.Name)}
    return names, members


def _dotted_exists(name: str) -> bool:
    """`locks.FolderLock`, `e3cm_bench.register`: a module of the package, then attributes."""
    parts = name.removeprefix("e3cm_bench.").split(".") if name != "e3cm_bench" else []
    for split in range(len(parts), -1, -1):
        try:
            obj = importlib.import_module(".".join(["e3cm_bench", *parts[:split]]))
        except ModuleNotFoundError:
            continue
        try:
            for attr in parts[split:]:
                obj = getattr(obj, attr)
        except AttributeError:
            return False
        return True
    return False


def doc_objects(text: str) -> list[str]:
    """The code objects a page names in backticks: `RunFolder`, `PROTOCOLS`, `run_benchmark`,
    `RunFolder.lock`, `locks.FolderLock`, `e3cm_bench.register(...)`. Plain lowercase words
    (`import`, `demo`: commands), paths and file names are not objects."""
    found = []
    for token in re.findall(r"`([A-Za-z_][\w.]*)(?:\(\.*\))?`", text):
        if token.startswith("__") or re.search(r"\.(py|ya?ml|h5|csv|md|json|npz)$", token):
            continue  # a path or a file name
        if "." in token or re.fullmatch(r"[A-Z][a-z]\w*|[A-Z][A-Z0-9_]+|[a-z0-9]+(?:_[a-z0-9]+)+", token):
            found.append(token)
    return sorted(set(found))


def test_every_object_docs_architecture_names_exists():
    """A class, constant, function or attribute the page names is defined in the package."""
    names, members = _definitions()
    objects = doc_objects((REPO / "docs" / "architecture.md").read_text())
    assert len(objects) > 30

    def exists(token: str) -> bool:
        head, _, rest = token.partition(".")
        if not rest and token != "e3cm_bench":
            return token in names
        if head[0].isupper():  # Class.attribute
            return head in members and rest in members[head]
        return _dotted_exists(token)

    missing = [t for t in objects if not exists(t)]
    assert not missing, f"docs/architecture.md names objects the package does not define: {', '.join(missing)}"


def test_the_object_check_fails_on_a_name_that_is_gone():
    names, members = _definitions()
    assert doc_objects("`RunFolder.lock`, `locks.FolderLock`, `e3cm_bench.register(...)`, `demo`, `run/folder.py`, "
                       "`NoSuchThing`, `config.yaml`") == ["NoSuchThing", "RunFolder.lock", "e3cm_bench.register",
                                                           "locks.FolderLock"]
    assert "lock" in members["RunFolder"] and "NoSuchThing" not in names
    assert _dotted_exists("ground.locks.FolderLock") and _dotted_exists("e3cm_bench.register")
    assert not _dotted_exists("ground.files.NoSuchLock") and not _dotted_exists("nosuchmodule.x")


def _calls(path: Path) -> list[tuple[int, str]]:
    """(line, dotted callee) of every call in a module: `MethodSpec.create(...)` -> 'MethodSpec.create'."""
    def dotted(node) -> str:
        if isinstance(node, ast.Name):
            return node.id
        if isinstance(node, ast.Attribute):
            return f"{dotted(node.value)}.{node.attr}"
        return "?"

    tree = ast.parse(path.read_text(), str(path))
    return [(node.lineno, dotted(node.func)) for node in ast.walk(tree) if isinstance(node, ast.Call)]


def callers(callee: str) -> list[str]:
    """'module.py:line' of every call of `callee` (a name as spelled at the call) in the package."""
    return [f"{path.relative_to(PACKAGE).as_posix()}:{line}" for path in sorted(PACKAGE.rglob("*.py"))
            for line, name in _calls(path) if name == callee]


def test_every_method_is_made_through_the_one_path():
    """A MethodSpec comes from a user's options through method.build_method only (the benchmark
    commands, `reproduce`, `match`, `calibrate` and `demo` alike, Benchmark.resolve_method being
    build_method with a benchmark); from a run's record through MethodSpec.from_identity."""
    made = [where for where in callers("MethodSpec.create") if not where.startswith("method/spec.py:")]
    direct = [where for where in callers("MethodSpec") if not where.startswith("method/spec.py:")]
    assert not made and not direct, f"MethodSpec.create outside method.py: {made}; MethodSpec(...) outside method.py: {direct}"
    assert callers("MethodSpec.create") and callers("build_method")



def test_every_request_is_made_by_the_one_resolver():
    """A RunRequest is constructed in pipeline/resolve.py only (resolve_request; the Python API's
    keywords through request_from_fields): no `RunRequest(...)`, no `cls(...)` in request.py, and
    the older keyword path RunRequest.of is gone; a request changes only by RunRequest.but."""
    direct = [where for where in callers("RunRequest") if not where.startswith("pipeline/resolve.py:")]
    assert not direct, f"RunRequest(...) outside pipeline/resolve.py: {direct}"
    assert not callers("RunRequest.of")
    assert any(w.startswith("benchmarks/eval_settings.py:") for w in callers("cls"))  # the scan sees cls(...)
    assert not [w for w in callers("cls") if w.startswith("pipeline/request.py:")]
    assert {w.split(":")[0] for w in callers("RunRequest")} == {"pipeline/resolve.py"}
    assert callers("request_from_fields") and callers("resolve_request")

# The same word naming another concept: glue-factory's MegaDepth layout, its evaluation protocol;
# COLMAP's own geometric verification, an sfm protocol setting (--verification colmap).
OTHER_MEANINGS = {"gluefactory": {"datasets/megadepth.py", "method/protocols.py"},
                  "colmap": {"sfm/protocol.py", "sfm/mapper.py", "matchers/base.py",  # base: the extra
                             "benchmarks/eval_options.py"}}  # --verification colmap


def _declared_formats() -> dict[str, str]:
    """Format name -> the module that declares it (a `Format` subclass with `name = "..."`)."""
    found = {}
    for path in sorted((PACKAGE / "interchange").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ClassDef) and any(getattr(b, "id", None) == "Format" for b in node.bases):
                for item in node.body:
                    if isinstance(item, ast.Assign) and any(getattr(t, "id", None) == "name" for t in item.targets):
                        assert item.value.value not in found, f"format {item.value.value!r} declared twice"
                        found[item.value.value] = path.relative_to(PACKAGE).as_posix()
    return found


def test_each_interchange_format_is_declared_in_one_module():
    """A format (its reader, writer, pixel origin) is one class in its own module of interchange/,
    and no other module spells its name: import, export and the docs read the registry."""
    declared = _declared_formats()
    assert len(declared) >= 4 and len(set(declared.values())) == len(declared), declared
    elsewhere = [f"{where}:{line}: {name!r}" for name, home in sorted(declared.items())
                 for path in sorted(PACKAGE.rglob("*.py"))
                 if (where := path.relative_to(PACKAGE).as_posix()) != home and where not in OTHER_MEANINGS.get(name, ())
                 for line, text in _string_literals(path) if text == name]
    assert not elsewhere, "a format's name outside its module:\n" + "\n".join(elsewhere)


# The kinds of run, each a hook of the one pipeline (pipeline/driver.py), and the module of each.
HOOKS = {"BenchmarkRun": "pipeline/runner.py", "ImportRun": "pipeline/imported.py", "MergeRun": "pipeline/shards.py",
         "CalibrationRun": "apps/calibration/run.py"}


def _classes() -> dict[str, tuple[str, list[str]]]:
    """Class name -> (module path relative to the package, its bases' names)."""
    found = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ClassDef):
                found[node.name] = (path.relative_to(PACKAGE).as_posix(), [getattr(b, "id", "") for b in node.bases])
    return found


def test_every_kind_of_run_is_a_hook_of_the_one_pipeline():
    """A benchmark run, an import, a shard merge and a calibration are RunHook objects (PairRun
    is the hook of a run scored pair by pair), each run through run_pipeline from its own module
    (the noise ensemble's draws are benchmark runs); only the pipeline opens a run folder, and
    only the pipeline and export (which reads a run under it, never writes one) take its lock."""
    classes = _classes()
    hooks = {name for name, (_, bases) in classes.items() if {"RunHook", "PairRun"} & set(bases)} - {"PairRun"}
    assert {name: classes[name][0] for name in hooks} == HOOKS
    assert {where.split(":")[0] for where in callers("run_pipeline")} == set(HOOKS.values())
    assert {where.split(":")[0] for where in callers("open_run")} == {"pipeline/driver.py"}
    locks = [f"{path.relative_to(PACKAGE).as_posix()}:{line}" for path in sorted(PACKAGE.rglob("*.py"))
             for line, name in _calls(path) if name.endswith(".lock") and name != "RunFolder.lock"]
    others = [where for where in locks if not where.startswith(("pipeline/driver.py:", "pipeline/export.py:"))]
    assert locks and not others, f"a run folder locked outside the pipeline: {others}"


# Imports from a package to one after it in the roles' order (code_shape.ROLES), each with why:
# none. The benchmark registry's lookups by name (importlib) are the only steps up, listed here.
UPWARD: dict[tuple[str, str], str] = {}
BY_NAME_UP = {
    "e3cm_bench.sfm.benchmark": "the multi-view benchmark: the registry's, its views and mapper sfm's (ELSEWHERE)",
    "e3cm_bench.sfm.own_images": "reconstruct's benchmark, no command, found by the name its runs record (UNLISTED)",
}


def test_imports_run_down_the_roles():
    """No import, at a module's top or in a function, runs from a package to one after it in the
    roles' order but the listed ones; at most 3 steps up in all, lookups by name included."""
    up = code_shape().upward_imports()
    assert set(up) == set(UPWARD), f"imports that run up the roles: {sorted(set(up) - set(UPWARD))}; " \
                                   f"listed but gone: {sorted(set(UPWARD) - set(up))}"
    assert len(UPWARD) + len(BY_NAME_UP) <= 3


def test_the_registry_looks_up_by_name_only_the_listed_modules():
    import e3cm_bench.benchmarks as registry

    named = set(registry.ELSEWHERE.values()) | {module for module, _ in registry.UNLISTED.values()}
    assert named == set(BY_NAME_UP)
    assert {registry.get_benchmark(name).name for name in (*registry.ELSEWHERE, *registry.UNLISTED)} == {"sfm", "reconstruct"}


def test_the_role_scan_finds_an_import_that_runs_up(tmp_path):
    files = {"__init__.py": "", "ground/__init__.py": "", "ground/a.py": "def f():\n    from p.cli import b\n",
             "cli/__init__.py": "", "cli/b.py": "from p.ground import a\n"}
    for name, text in files.items():
        (tmp_path / "p" / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / "p" / name).write_text(text)
    assert code_shape().upward_imports(tmp_path / "p") == [("p.ground.a", "p.cli"), ("p.ground.a", "p.cli.b")]


def test_every_package_has_a_role_and_the_top_level_only_the_face():
    shape = code_shape()
    packages = {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").is_file()}
    assert packages == set(shape.ROLES), (sorted(packages - set(shape.ROLES)), sorted(set(shape.ROLES) - packages))
    assert {p.name for p in PACKAGE.glob("*.py")} == {"__init__.py", "__main__.py"}