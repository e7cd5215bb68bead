"""One resolution of each default, read from the source (ast) as docs/architecture.md states it:
the protocol, the matching side, --pair-timeout and the pixel origin are each read in one
function, which the commands, `reproduce`, `import`/`export` and the Python API call. A second
place that reads a default drifts from the first (a WxBS config without `protocol:` once got
e3cm-bench's own estimator under `reproduce` and the reference's under `e3cm-bench wxbs`)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "e3cm_bench"

# default -> (the module of its one resolver, the resolver, modules that must call it). The
# table docs/architecture.md cites ("One resolution of each default").
RESOLVERS = {
    "protocol": ("e3cm_bench/method/protocols.py", "resolve_protocol",
                 ("e3cm_bench/method/spec.py", "e3cm_bench/benchmarks/base.py", "e3cm_bench/cli/benchmarks.py",
                  "e3cm_bench/pipeline/experiments.py")),
    "max_side": ("e3cm_bench/method/protocols.py", "resolve_max_side",
                 # reconstruct's side: build_method's, through the run resolver (pipeline/resolve.py)
                 ("e3cm_bench/method/spec.py", "e3cm_bench/benchmarks/base.py")),
    "pair_timeout": ("e3cm_bench/pipeline/match_options.py", "resolve_pair_timeout",
                     ("e3cm_bench/pipeline/match_options.py",)),
    "pixel_origin": ("e3cm_bench/interchange/pixels.py", "resolve_origin",
                     ("e3cm_bench/pipeline/export.py", "e3cm_bench/interchange/colmap.py",
                      "e3cm_bench/interchange/gluefactory.py", "e3cm_bench/interchange/hloc.py",
                      "e3cm_bench/interchange/npz.py")),
}
# Reads that are not a run's default, each with why.
NOT_A_RUN_DEFAULT = {
    # A record written before protocols were recorded ran under e3cm-bench's own: the record's
    # fact, not the default of a new run.
    ("protocol", "e3cm_bench/storage/run_config.py", "protocol"),
}
# Reads in modules being rewritten into one pipeline (issue 63, point 2), left to that rewrite:
# run_benchmark, run_methods and import_run without `ev` take EvalSettings(), protocol `default`
# on WxBS and EVD too, where `benchmark.resolve_eval()` gives the benchmark's (wxbs).
PENDING: set = set()  # none left: the pipeline's RunRequest resolves them


def _named(node: ast.AST, names: set[str]) -> bool:
    return (isinstance(node, ast.Name) and node.id in names) or (isinstance(node, ast.Attribute) and node.attr in names)


def _fallbacks(tree: ast.AST, names: set[str]) -> list[ast.AST]:
    """`x or <names>`, `<names> or x`, `<names> if ... else x`: a default filled in where it is read."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.BoolOp) and isinstance(node.op, ast.Or) and any(_named(v, names) for v in node.values):
            found.append(node)
        elif isinstance(node, ast.IfExp) and (_named(node.body, names) or _named(node.orelse, names)):
            found.append(node)
    return found


def _parameter_defaults(tree: ast.AST, name: str) -> list[ast.AST]:
    """The defaults given to a parameter or dataclass field called `name`, and the third element
    of a command's option tuple ("name", TypedOpt, default) (cli/benchmarks.py common_after)."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            args = node.args
            positional = args.posonlyargs + args.args
            pairs = list(zip(positional[len(positional) - len(args.defaults):], args.defaults))
            pairs += [(a, d) for a, d in zip(args.kwonlyargs, args.kw_defaults) if d is not None]
            found += [d for a, d in pairs if a.arg == name]
        elif isinstance(node, ast.AnnAssign) and _named(node.target, {name}) and node.value is not None:
            found.append(node.value)
        elif (isinstance(node, ast.Tuple) and len(node.elts) == 3 and isinstance(node.elts[0], ast.Constant)
              and node.elts[0].value == name):
            found.append(node.elts[2])
    return found


def reads(default: str, tree: ast.AST) -> list[ast.AST]:
    """Where a module's source reads `default`'s value when none is given."""
    if default == "protocol":  # the benchmark's default protocol, a literal in its place, or EvalSettings' own
        calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call)]
        return [n for n in ast.walk(tree) if isinstance(n, ast.Attribute) and n.attr == "default_protocol"] + [
            n for n in calls if isinstance(n.func, ast.Attribute) and n.func.attr == "get" and len(n.args) == 2
            and isinstance(n.args[0], ast.Constant) and n.args[0].value == "protocol"] + [
            n for n in calls if _named(n.func, {"EvalSettings"})  # its field's "default", not the benchmark's
            and not any(k.arg in ("protocol", None) for k in n.keywords)]
    if default == "max_side":  # the benchmark's default side
        return [n for n in ast.walk(tree) if isinstance(n, ast.Attribute) and n.attr == "default_max_side"]
    if default == "pair_timeout":  # a fallback, a check against a number, a default other than None
        names = {"pair_timeout", "time_limit"}
        compared = [n for n in ast.walk(tree) if isinstance(n, ast.Compare) and _named(n.left, names)
                    and any(isinstance(c, ast.Constant) and isinstance(c.value, (int, float)) for c in n.comparators)]
        others = [d for d in _parameter_defaults(tree, "pair_timeout") if not (isinstance(d, ast.Constant) and d.value is None)]
        return _fallbacks(tree, names) + compared + others
    if default == "pixel_origin":  # a format's own origin filled in for an origin not given
        return _fallbacks(tree, {"origin"}) + [d for d in _parameter_defaults(tree, "origin") if _named(d, {"origin"})]
    raise KeyError(default)


def _functions(tree: ast.AST) -> list[tuple[ast.AST, str]]:
    """(node, name of the innermost function holding it) for every node under a function."""
    held = []

    def visit(node, owner):
        for child in ast.iter_child_nodes(node):
            inner = child.name if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)) else owner
            held.append((child, inner))
            visit(child, inner)

    visit(tree, "<module>")
    return held


def places(default: str, root: Path = REPO, files=None) -> list[tuple[str, str]]:
    """(module, function) of every read of `default` in the package (and scripts/)."""
    found = []
    for path in files or sorted([*PACKAGE.rglob("*.py"), *(REPO / "scripts").rglob("*.py")]):
        text = path.read_text()
        if default == "pixel_origin" and "interchange" not in text:
            continue  # `origin` means a pixel origin only where the formats are in use (importlib's spec.origin is not one)
        tree = ast.parse(text, str(path))
        hits = {id(n) for n in reads(default, tree)}
        module = path.relative_to(root).as_posix()
        found += [(module, owner) for node, owner in _functions(tree) if id(node) in hits]
    return found


@pytest.mark.parametrize("default", RESOLVERS)
def test_each_default_is_read_in_its_one_resolver(default):
    module, resolver, _ = RESOLVERS[default]
    found = [(m, f) for m, f in places(default) if (default, m, f) not in NOT_A_RUN_DEFAULT | PENDING]
    assert (module, resolver) in found, f"the scan no longer sees {resolver} read the {default} default"
    assert set(found) == {(module, resolver)}, f"the {default} default is read outside {resolver}: {found}"


def test_the_pending_reads_are_still_there():
    # once the pipeline's rewrite resolves them, PENDING must shrink with it
    for default, module, function in PENDING:
        assert (module, function) in places(default, REPO, [REPO / module]), (default, module, function)


@pytest.mark.parametrize("default", RESOLVERS)
def test_the_commands_and_the_api_call_the_resolver(default):
    _, resolver, callers = RESOLVERS[default]
    for caller in callers:
        tree = ast.parse((REPO / caller).read_text())
        calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call) and _named(n.func, {resolver})]
        assert calls, f"{caller} no longer calls {resolver}"


@pytest.mark.parametrize(("default", "source"), [
    ("protocol", "def f(bench, given):\n    return given or bench.default_protocol\n"),
    ("protocol", "def f(experiment):\n    return experiment.get('protocol', 'default')\n"),
    ("protocol", "def f(seed):\n    return EvalSettings(seed=seed)\n"),
    ("max_side", "def f(bench, side):\n    return bench.default_max_side if side is None else side\n"),
    ("pair_timeout", "def f(o):\n    return o.pair_timeout or 60\n"),
    ("pair_timeout", "def f(pair_timeout: float = 30.0):\n    pass\n"),
    ("pair_timeout", "def f(o):\n    assert o.pair_timeout > 0\n"),
    ("pixel_origin", "def f(origin, fmt):\n    return origin or fmt.origin\n"),
    ("pixel_origin", "def f(origin, fmt):\n    return fmt.origin if origin is None else origin\n"),
    ("pixel_origin", "def write(out, origin: str = NpzFormat.origin):\n    pass\n"),
])
def test_the_scan_sees_a_second_reading(tmp_path, default, source):
    # each kind of read the scan looks for, written outside the resolver, is found
    path = tmp_path / "elsewhere.py"
    path.write_text(f"# e3cm_bench.interchange\n{source}")
    assert places(default, tmp_path, [path]) == [("elsewhere.py", source.split("(")[0][4:])]  # def NAME(


def test_a_declared_pair_timeout_means_not_given():
    # the commands' option tuples and MatchOptions declare it unset: resolve_pair_timeout says what that is
    found = places("pair_timeout", REPO, [PACKAGE / "cli" / "benchmarks.py", PACKAGE / "pipeline" / "match_options.py"])
    assert found == [("e3cm_bench/pipeline/match_options.py", "resolve_pair_timeout")]
    tree = ast.parse((PACKAGE / "cli" / "benchmarks.py").read_text())
    assert _parameter_defaults(tree, "pair_timeout"), "the scan no longer sees the command's --pair-timeout default"
