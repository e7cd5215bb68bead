"""What a plugin's matcher is, for a run's record: the hash of its code, and its settings.

A plugin's identity is its code, not its distribution's version: an editable install (``pip
install -e``) keeps its name and version through every edit, so a version alone would let a
folder of the old code's matches resume, and be scored, as the new code's. The hash is taken
from the files Python imports, found through the module (``__file__``, and a package's
``__path__``, i.e. its spec's submodule_search_locations), never from the distribution's file
list (RECORD), which an editable install never updates.

- a module outside any package: the sha256 of its file (the digest a file tool gives);
- a module inside a package, and an entry point's package: every ``.py`` file of its top-level
  package, each named by its path inside the package, hashed together (a helper module it
  imports from the same package changes the identity as well).

Settings (config.yaml's ``matcher`` block) are what the matcher says of itself: a ``settings()``
method where it has one, else its ``config()`` where it defines one (as the built-ins do), else
what it was built with: the entry's settings dataclass with every default, or the arguments of
the factory (``module:factory``) or of the entry's build function, defaults included.
"""

from __future__ import annotations

import dataclasses
import hashlib
import inspect
import sys
from pathlib import Path
from types import ModuleType

from e3cm_bench.ground.files import file_sha256

SKIPPED_FOLDERS = ("__pycache__",)


def package_files(module: ModuleType) -> list[tuple[str, Path]]:
    """(name inside the package, file) of every .py file of a package module, sorted by name."""
    found = {}
    for base in getattr(module, "__path__", None) or []:
        base = Path(base)
        for path in sorted(base.rglob("*.py")):
            parts = path.relative_to(base).parts
            if any(p in SKIPPED_FOLDERS or p.startswith(".") for p in parts[:-1]):
                continue
            found.setdefault("/".join(parts), path)  # a namespace package's first copy, as import finds it
    return sorted(found.items())


def code_sha256(module_name: str) -> str | None:
    """The hash of the code behind an imported module: its file alone when it is not in a package
    (file_sha256 of it), else every .py file of its top-level package; None where Python loaded
    it from no file (a module built in memory)."""
    top = sys.modules.get(module_name.split(".")[0])
    if top is not None and getattr(top, "__path__", None) is not None:
        files = package_files(top)
        if files:
            digest = hashlib.sha256()
            for name, path in files:
                digest.update(f"{name}\0{file_sha256(path)}\n".encode())
            return digest.hexdigest()
    module = sys.modules.get(module_name)
    file = getattr(module, "__file__", None)
    return file_sha256(Path(file)) if file and Path(file).is_file() else None


def bound_defaults(function, skip_first: bool = False) -> dict:
    """A callable's arguments when called without any (its defaults), as YAML can write them
    (an object that is no plain value is written as its repr); skip_first: leave out the first
    parameter (the settings an entry's build function is given)."""
    try:
        parameters = list(inspect.signature(function).parameters.values())
    except (TypeError, ValueError):  # a builtin without a signature
        return {}
    if skip_first and parameters:
        parameters = parameters[1:]
    kinds = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    return {p.name: _plain(p.default) for p in parameters
            if p.kind in kinds and p.default is not inspect.Parameter.empty}


def built_with(entry, instance) -> dict:
    """The settings a plugin's matcher was built from: its settings dataclass (all fields), else
    the factory's arguments (a module:factory's build carries it as ``factory``), else the
    entry's build function's own (past the settings it is given)."""
    if instance is not None and dataclasses.is_dataclass(instance):
        return {k: _plain(v) for k, v in dataclasses.asdict(instance).items()}
    factory = getattr(entry.build, "factory", None)
    if factory is not None:
        return bound_defaults(factory)
    return bound_defaults(entry.build, skip_first=True)


def _plain(value):
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    return repr(value)
