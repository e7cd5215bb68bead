"""MkDocs build hooks: measured tables rendered from the committed CSVs, the CLI reference
written by Typer from the app itself. Nothing in the site is retyped from a run.

In a page:
    {{ csv_table("results/sample/table1_hpatches/table.csv", columns=[...], where="source == 'measured'",
                 rename={...}, decimals=2, pivot={"index": ..., "columns": ..., "values": ...}) }}
    {{ cli_reference }}
    {{ layer_table }}
    {{ role_table }}
    {{ format_table }}
Paths are relative to the repository root (the folder of mkdocs.yml). Only literals are
accepted as arguments (read with ast.literal_eval): a page cannot run code.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

MACRO = re.compile(r"\{\{\s*(csv_table\(.*?\)|cli_reference|layer_table|role_table|format_table)\s*\}\}", re.S)
ROOT = Path(__file__).resolve().parents[1]


# Figures the pages show, kept where the runs wrote them: added to the site as they are.
FIGURES = ("results/**/*.png", "results/**/*.jpg")


def on_files(files, config):
    from mkdocs.structure.files import File

    root = Path(config["config_file_path"]).resolve().parent
    for pattern in FIGURES:
        for path in sorted(root.glob(pattern)):
            files.append(File(path.relative_to(root).as_posix(), str(root), config["site_dir"], config["use_directory_urls"]))
    return files


def on_page_markdown(markdown: str, page, config, files) -> str:
    root = Path(config["config_file_path"]).resolve().parent
    return MACRO.sub(lambda m: render(m.group(1), root, page.file.src_path), markdown)


def render(call: str, root: Path, page: str) -> str:
    """One macro's Markdown; a broken macro, a missing file or column fails the build in one line."""
    from mkdocs.exceptions import PluginError

    try:
        if call == "cli_reference":
            return cli_reference()
        if call == "layer_table":
            return layer_table(root)
        if call == "role_table":
            return role_table(root)
        if call == "format_table":
            return format_table()
        node = ast.parse(call, mode="eval").body
        args = [ast.literal_eval(a) for a in node.args]
        kwargs = {k.arg: ast.literal_eval(k.value) for k in node.keywords}
        return csv_table(root, *args, page=page, **kwargs)
    except (ValueError, SyntaxError, KeyError, TypeError) as error:
        raise PluginError(f"{page}: {error}") from None


def csv_table(root: Path, path: str, columns=None, where: str | None = None, rename: dict | None = None,
              decimals=None, pivot: dict | None = None, page: str = "", intervals: bool = True) -> str:
    """A Markdown table of the CSV at root/path: rows filtered by `where` (a pandas query),
    optionally pivoted, the `columns` in order, renamed, numbers rounded to `decimals`
    (one number, or per column). A missing file or column fails the build, naming both.
    A shown column with ``<col>_lo`` and ``<col>_hi`` in the CSV (a bootstrap interval) shows
    them in its cells, ``0.73 [0.53, 0.93]``, rounded as the number; intervals=False: the number alone."""
    import pandas as pd

    file = root / path
    if not file.is_file():
        raise ValueError(f"{page}: csv_table: {path} not found")
    table = pd.read_csv(file)
    bounds = table.copy()
    if where:
        table = table.query(where)
    if pivot:
        table = table.pivot(index=pivot["index"], columns=pivot["columns"], values=pivot["values"]).reset_index()
        table.columns = [str(c) for c in table.columns]
    if columns:
        missing = [c for c in columns if c not in table.columns]
        if missing:
            raise ValueError(f"{page}: csv_table: {path} has no column(s) {', '.join(missing)}")
        table = table[list(columns)]
    header = [(rename or {}).get(c, c) for c in table.columns]
    numeric = [pd.api.types.is_numeric_dtype(table[c]) for c in table.columns]

    def cell(value, column) -> str:
        if isinstance(value, float) and value != value:
            return ""
        places = decimals.get(column) if isinstance(decimals, dict) else decimals
        if places is not None and isinstance(value, (int, float)) and not isinstance(value, bool):
            return f"{value:.{places}f}"
        if isinstance(value, float) and value.is_integer():
            return str(int(value))
        return str(value).replace("|", "\\|")

    def with_interval(index, value, column) -> str:
        text = cell(value, column)
        if not intervals or pivot or f"{column}_lo" not in bounds.columns or f"{column}_hi" not in bounds.columns:
            return text
        lo, hi = bounds.at[index, f"{column}_lo"], bounds.at[index, f"{column}_hi"]
        if text == "" or lo != lo or hi != hi:
            return text
        return f"{text} [{cell(float(lo), column)}, {cell(float(hi), column)}]"

    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---:" if n else "---" for n in numeric) + "|"]
    for index, row in table.iterrows():
        lines.append("| " + " | ".join(with_interval(index, row[c], c) for c in table.columns) + " |")
    return "\n".join(lines) + f"\n\n<small>Rendered at build time from `{path}`.</small>\n"


def cli_reference() -> str:
    """Every command's usage, arguments and options, as Typer writes them for the app."""
    import typer
    from typer.cli import get_docs_for_click

    from e3cm_bench.cli import app

    command = typer.main.get_command(app)
    text = get_docs_for_click(obj=command, ctx=typer.Context(command), name="e3cm-bench", title="e3cm-bench")
    return re.sub(r"^# e3cm-bench\n", "", text)


def format_table() -> str:
    """The interchange formats as their registry declares them (e3cm_bench/interchange/registry.py)."""
    from e3cm_bench.interchange.registry import formats

    rows = [f"| {f.name} | `import --{f.name} {' '.join(f.reads)}` | `export --to {f.name}`: {f.writes} | {f.origin} |"
            for f in formats().values()]
    return "\n".join(["| format | import | export | pixel origin |", "|---|---|---|---|", *rows])


def _code_shape(root: Path):
    """scripts/maintain/code_shape.py, the one reader of the import graph (tests/test_architecture.py reads it too)."""
    import importlib.util
    import sys

    if "code_shape" not in sys.modules:
        script = min((root / "scripts").rglob("code_shape.py"))  # scripts/ or a folder of it
        spec = importlib.util.spec_from_file_location("code_shape", script)
        shape = importlib.util.module_from_spec(spec)
        sys.modules["code_shape"] = shape  # its dataclasses look the module up while it loads
        spec.loader.exec_module(shape)
    return sys.modules["code_shape"]


def role_table(root: Path) -> str:
    """The packages by role, lowest first, with their modules, and the imports that run up (none
    but those the page lists), as the code has them now."""
    shape = _code_shape(root)
    package = root / "e3cm_bench"
    up = shape.upward_imports(package)
    return (f"{shape.role_table(package)}\n\n<small>Rendered at build time (`scripts/maintain/code_shape.py --roles`): "
            f"{len(up)} import(s) from a package to one after it"
            + "".join(f"; `{a}` -> `{b}`" for a, b in up) + ".</small>\n")


def layer_table(root: Path) -> str:
    """The package's layers as its module-level imports and the package __init__s they run make
    them now (scripts/maintain/code_shape.py computes them, the same graph tests/test_architecture.py reads)."""
    shape = _code_shape(root)
    package = root / "e3cm_bench"
    depth = shape.layers(shape.import_graph(package))
    return (f"{len(depth)} modules in {max(depth.values()) + 1} layers.\n\n{shape.layer_table(package)}\n\n"
            "<small>Rendered at build time from the package's module-level imports and the package "
            "`__init__`s they run (`scripts/maintain/code_shape.py --layers`).</small>\n")
