"""The shape of the package, read from its source with ast: modules by size, the longest
functions, and the layers its imports make.

    python scripts/maintain/code_shape.py                 # modules by size, the 15 longest functions,
                                                          # the functions over 8 parameters
    python scripts/maintain/code_shape.py --layers        # the layer table docs/architecture.md shows
    python scripts/maintain/code_shape.py --roles         # the packages by role, and any import that runs up

A module's layer is the length of the longest chain of imports that run when it is imported,
inside the package: a module that imports none of the package's modules is layer 0, one that
imports only those is layer 1, and so on. Importing ``a.b.c`` runs ``a/__init__`` and
``a/b/__init__`` first, so those are edges too (but for the packages the importer lies in:
Python has begun them before its first line). Imports inside functions are left out: they run on
first use, so they do not order the modules; most defer a heavy library (torch, scipy,
matplotlib) so that the command line starts fast, and a few would close a cycle through a
package ``__init__`` (tests/test_architecture.py lists those). Imports under
``if TYPE_CHECKING:`` never run and are left out too; so are ``importlib.import_module`` calls
(the benchmark registry's discovery, the package face's names on first use).

tests/test_architecture.py reads the import graph from here, so the layer table, the cycle test
and this script see the same edges. A measurement, not a gate: nothing here fails.
"""

from __future__ import annotations

import argparse
import ast
from dataclasses import dataclass
from pathlib import Path

# The checkout's root, wherever under scripts/ this file lies.
REPO = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())
PACKAGE = REPO / "e3cm_bench"
MODULE_LINES = 400
FUNCTION_LINES = 60
PARAMETERS = 8  # a typer command's are exempt: each is a command-line option


def module_name(path: Path, package: Path = PACKAGE) -> str:
    parts = list(path.relative_to(package.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def package_modules(package: Path = PACKAGE) -> dict[str, Path]:
    """Dotted name -> source file of every module of the package (a package is its __init__)."""
    return {module_name(p, package): p for p in sorted(package.rglob("*.py"))}


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or \
        (isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _module_level_imports(tree: ast.Module) -> list[ast.Import | ast.ImportFrom]:
    """The import statements that run when the module is imported: at the top level, in class
    bodies and in try/if/with blocks, not in functions nor under `if TYPE_CHECKING:`."""
    found: list[ast.Import | ast.ImportFrom] = []

    def visit(statements: list[ast.stmt]) -> None:
        for node in statements:
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                found.append(node)
            elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            elif isinstance(node, ast.If) and _is_type_checking(node.test):
                visit(node.orelse)
            else:
                for name in ("body", "orelse", "finalbody", "handlers"):
                    block = getattr(node, name, None)
                    if isinstance(block, list):
                        visit([s for s in block if isinstance(s, (ast.stmt, ast.excepthandler))])
                if isinstance(node, ast.ExceptHandler):
                    visit(node.body)

    visit(tree.body)
    return found


def _all_imports(tree: ast.Module) -> list[ast.Import | ast.ImportFrom]:
    return [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))]


def _targets(node: ast.Import | ast.ImportFrom, module: str, is_package: bool, known: set[str]) -> set[str]:
    """The package's modules an import statement names."""
    if isinstance(node, ast.Import):
        return {a.name for a in node.names if a.name in known}
    if node.level:
        base = module.split(".") if is_package else module.split(".")[:-1]
        base = base[: len(base) - (node.level - 1)]
        source = ".".join(base + ([node.module] if node.module else []))
    else:
        source = node.module or ""
    out = set()
    for alias in node.names:
        if f"{source}.{alias.name}" in known:  # `from . import metrics`: a submodule
            out.add(f"{source}.{alias.name}")
        elif source in known:
            out.add(source)
    return out


def _packages_of(module: str) -> set[str]:
    """The packages Python imports before `module` (its parents: `a`, `a.b` for `a.b.c`)."""
    parts = module.split(".")
    return {".".join(parts[:k]) for k in range(1, len(parts))}


def import_graph(package: Path = PACKAGE, module_level: bool = True, packages: bool = True) -> dict[str, set[str]]:
    """Module -> the package's modules its imports run (module-level imports only, by default).

    Importing ``a.b.c`` runs ``a/__init__`` and ``a/b/__init__`` before ``a/b/c``: with
    packages=True (the default) those are edges too, except the packages the importer itself
    lies in (Python has begun them before the importer's first line, so importing it runs
    nothing of theirs again)."""
    modules = package_modules(package)
    known = set(modules)
    graph = {}
    for name, path in modules.items():
        tree = ast.parse(path.read_text(), str(path))
        statements = _module_level_imports(tree) if module_level else _all_imports(tree)
        is_package = path.name == "__init__.py"
        targets = {t for node in statements for t in _targets(node, name, is_package, known)}
        if packages:
            begun = _packages_of(name) | {name}
            targets |= {p for t in targets for p in _packages_of(t) if p in known} - begun
        graph[name] = targets - {name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm), each
    sorted: every import cycle lies inside one."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            connect(v)
    return found


def cycle_closing(package: Path = PACKAGE) -> set[tuple[str, str]]:
    """The function-level imports that would close an import cycle if moved to their module's
    top: (importer, imported) edges, package __init__ edges included, absent from the
    module-level graph and making it cyclic when added alone."""
    eager, every = import_graph(package), import_graph(package, module_level=False)
    return {(a, b) for a in every for b in every[a] - eager[a] if cycles({**eager, a: eager[a] | {b}})}


def lazy_cycle_edges(package: Path = PACKAGE) -> set[tuple[str, str]]:
    """The function-level imports that lie on a cycle of the graph of every import (functions'
    too, package __init__ edges included): (importer, imported) edges absent from the
    module-level graph whose two ends share a strongly connected component."""
    eager, every = import_graph(package), import_graph(package, module_level=False)
    component = {v: k for k, found in enumerate(cycles(every)) for v in found}
    return {(a, b) for a in every for b in every[a] - eager[a] if a in component and component.get(b) == component[a]}


def layers(graph: dict[str, set[str]]) -> dict[str, int]:
    """Module -> the length of the longest import chain below it (0: imports none of the package)."""
    depth: dict[str, int] = {}

    def layer(v: str, path: tuple[str, ...]) -> int:
        if v in path:
            raise ValueError("import cycle: " + " -> ".join(path[path.index(v):] + (v,)))
        if v not in depth:
            depth[v] = 1 + max((layer(w, path + (v,)) for w in graph[v]), default=-1)
        return depth[v]

    for v in graph:
        layer(v, ())
    return depth


@dataclass(frozen=True)
class Function:
    module: str
    name: str  # Class.method or outer.inner
    line: int
    lines: int


def functions(package: Path = PACKAGE) -> list[Function]:
    """Every function and method, nested ones included, with its length in lines (decorators
    left out, its docstring in)."""
    found = []
    for name, path in package_modules(package).items():
        tree = ast.parse(path.read_text(), str(path))

        def visit(node: ast.AST, prefix: str) -> None:
            for child in ast.iter_child_nodes(node):
                if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    found.append(Function(name, prefix + child.name, child.lineno, child.end_lineno - child.lineno + 1))
                    visit(child, prefix + child.name + ".")
                elif isinstance(child, ast.ClassDef):
                    visit(child, prefix + child.name + ".")
                else:
                    visit(child, prefix)

        visit(tree, "")
    return found


@dataclass(frozen=True)
class Parameters:
    module: str
    name: str  # Class.method or outer.inner
    line: int
    count: int  # positional + keyword-only + *args + **kwargs; a method's self or cls not counted
    command: bool  # a typer command: typer reads each of its parameters as a command-line option


def _typer_commands(tree: ast.Module) -> set[str]:
    """The names of the module's functions typer registers as commands: decorated with
    ``X.command(...)`` (``@app.command()``), or handed, wrapped or not, to a ``X.command(...)``
    call (``app.command("import")(friendly_errors(_with_dataset_options(import_matches)))``).
    Only in a module that imports typer: elsewhere a ``.command`` means something else."""
    if not any((isinstance(n, ast.Import) and any(a.name == "typer" for a in n.names)) or
               (isinstance(n, ast.ImportFrom) and n.module == "typer") for n in ast.walk(tree)):
        return set()

    def registers(call: ast.AST) -> bool:
        return isinstance(call, ast.Call) and isinstance(call.func, ast.Attribute) and call.func.attr == "command"

    def handed(expr: ast.AST) -> set[str]:
        """The names an expression hands over: itself, or an argument of a wrapping call (not
        the wrappers: friendly_errors(f) hands over f)."""
        if isinstance(expr, ast.Name):
            return {expr.id}
        return {n for arg in expr.args for n in handed(arg)} if isinstance(expr, ast.Call) else set()

    found = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and any(map(registers, node.decorator_list)):
            found.add(node.name)
        elif isinstance(node, ast.Call) and registers(node.func):
            found |= {name for arg in node.args for name in handed(arg)}
    return found


def _count(node: ast.FunctionDef | ast.AsyncFunctionDef, in_class: bool) -> int:
    a = node.args
    positional = [p.arg for p in a.posonlyargs + a.args]
    static = any(isinstance(d, ast.Name) and d.id == "staticmethod" for d in node.decorator_list)
    bound = in_class and not static and positional[:1] in (["self"], ["cls"])
    return len(positional) - bound + len(a.kwonlyargs) + (a.vararg is not None) + (a.kwarg is not None)


def parameters(package: Path = PACKAGE) -> list[Parameters]:
    """Every function and method, nested ones included, with its number of parameters and
    whether typer makes a command of it (_typer_commands)."""
    found = []
    for name, path in package_modules(package).items():
        tree = ast.parse(path.read_text(), str(path))
        commands = _typer_commands(tree)

        def visit(node: ast.AST, prefix: str, in_class: bool) -> None:
            for child in ast.iter_child_nodes(node):
                if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    found.append(Parameters(name, prefix + child.name, child.lineno, _count(child, in_class),
                                            child.name in commands))
                    visit(child, prefix + child.name + ".", False)
                elif isinstance(child, ast.ClassDef):
                    visit(child, prefix + child.name + ".", True)
                else:
                    visit(child, prefix, False)

        visit(tree, "", False)
    return found


def module_lines(package: Path = PACKAGE) -> dict[str, int]:
    return {name: len(path.read_text().splitlines()) for name, path in package_modules(package).items()}


def layer_table(package: Path = PACKAGE) -> str:
    """Markdown: one row per layer, its modules (package-relative names)."""
    depth = layers(import_graph(package))
    rows = ["| layer | modules |", "|---:|---|"]
    for k in range(max(depth.values()) + 1):
        names = sorted(n.removeprefix(package.name + ".") for n, d in depth.items() if d == k)
        rows.append(f"| {k} | {', '.join(f'`{n}`' for n in names)} |")
    return "\n".join(rows)


# The packages by role, lowest first (docs/architecture.md, Packages by role): a module imports
# from its own package and those before it. The package face (e3cm_bench/__init__.py, __main__)
# stands with the command line, at the top.
ROLES = ("ground", "storage", "stats", "geometry", "backbones", "matching", "matchers", "method", "datasets",
         "interchange", "drawing", "benchmarks", "sfm", "paper", "reporting", "pipeline", "gate", "data", "apps", "cli")


def role(module: str) -> str:
    """A module's package by role: e3cm_bench.pipeline.runner -> pipeline; the face -> cli."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in ROLES else "cli"


def upward_imports(package: Path = PACKAGE) -> list[tuple[str, str]]:
    """(importer, imported) of every import, at a module's top or in a function, that runs from a
    package to one after it in ROLES."""
    graph = import_graph(package, module_level=False)
    rank = {name: k for k, name in enumerate(ROLES)}
    return sorted((a, b) for a, targets in graph.items() for b in targets if rank[role(b)] > rank[role(a)])


def role_table(package: Path = PACKAGE) -> str:
    """Markdown: one row per package by role, lowest first, with its modules."""
    names = sorted(package_modules(package))
    rows = ["| role | package | modules |", "|---:|---|---|"]
    for k, name in enumerate(ROLES):
        inside = [n.removeprefix(f"{package.name}.{name}").lstrip(".") or "__init__" for n in names
                  if role(n) == name and n.startswith(f"{package.name}.{name}")]
        rows.append(f"| {k} | `{name}/` | {', '.join(f'`{m}`' for m in inside)} |")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--layers", action="store_true", help="Print the layer table (Markdown) instead.")
    parser.add_argument("--roles", action="store_true", help="Print the packages by role (Markdown) instead.")
    parser.add_argument("--top", type=int, default=15, help="How many of the longest functions to list.")
    args = parser.parse_args(argv)
    if args.roles:
        up = upward_imports()
        print(role_table())
        print(f"\n{len(up)} import(s) from a package to one after it in the roles' order" + "".join(f"\n  {a} -> {b}" for a, b in up))
        return
    if args.layers:
        depth = layers(import_graph())
        print(f"{len(depth)} modules in {max(depth.values()) + 1} layers (module-level imports and the package __init__s they run)\n")
        print(layer_table())
        return
    sizes = sorted(module_lines().items(), key=lambda kv: (-kv[1], kv[0]))
    over = [n for n, k in sizes if k > MODULE_LINES]
    print(f"{len(sizes)} modules, {sum(k for _, k in sizes)} lines; {len(over)} over {MODULE_LINES} lines")
    for name, k in sizes:
        print(f"{k:6d}  {name}{'  *' if k > MODULE_LINES else ''}")
    every = sorted(functions(), key=lambda f: (-f.lines, f.module, f.line))
    long = [f for f in every if f.lines > FUNCTION_LINES]
    print(f"\n{len(every)} functions; {len(long)} over {FUNCTION_LINES} lines; the {args.top} longest:")
    for f in every[: args.top]:
        print(f"{f.lines:6d}  {f.module}.{f.name}  (line {f.line})")
    many = sorted((f for f in parameters() if f.count > PARAMETERS), key=lambda f: (-f.count, f.module, f.line))
    print(f"\n{sum(not f.command for f in many)} functions over {PARAMETERS} parameters "
          f"(and {sum(f.command for f in many)} typer commands, marked c):")
    for f in many:
        print(f"{f.count:6d}  {f.module}.{f.name}  (line {f.line}){'  c' if f.command else ''}")


if __name__ == "__main__":
    main()
