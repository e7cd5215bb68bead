"""Where the module of ``--matcher package.module:factory`` comes from, and nothing else.

A module on the Python path is imported as it is. Otherwise its top-level module or package is
looked for in the current folder, as ``python -m`` would, but only that name comes from the
folder: it is loaded by its file through a finder that answers for that one name, for the time
of the import; the folder never joins ``sys.path``. A folder holding the matcher may hold
anything else (a downloaded dataset with a ``PIL.py``, a ``json.py``): none of it is imported,
then or later, here or in the processes this one starts.

Those processes (--workers, SLURM array tasks) are given the module's file (USER_FILES_ENV),
never the folder, and are started without the current folder on their path
(`no_folder_on_path`: PYTHONSAFEPATH, which multiprocessing's spawn and submitit's
``python -m`` would otherwise honour by putting the folder first).
"""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import importlib.util
import json
import os
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

# top-level module name -> the file it was loaded from, for the processes this one starts
USER_FILES_ENV = "E3CM_BENCH_USER_MODULE_FILES"


def user_files() -> dict[str, str]:
    try:
        files = json.loads(os.environ.get(USER_FILES_ENV) or "{}")
    except ValueError:
        return {}
    return (
        {k: v for k, v in files.items() if isinstance(k, str) and isinstance(v, str)} if isinstance(files, dict) else {}
    )


class _OneName(importlib.abc.MetaPathFinder):
    """Finds the module `top` at `file` (a package where the file is an __init__.py); no other name."""

    def __init__(self, top: str, file: str) -> None:
        self.top, self.file = top, file

    def find_spec(self, fullname, path=None, target=None):
        if fullname != self.top:
            return None
        folder = [str(Path(self.file).parent)] if Path(self.file).name == "__init__.py" else None
        return importlib.util.spec_from_file_location(fullname, self.file, submodule_search_locations=folder)


def _file_of(top: str) -> str | None:
    """The file `top` must be loaded from: the one this process was given, else the current
    folder's where `top` is not found on the Python path; None: import as usual."""
    given = user_files().get(top)
    if given and Path(given).is_file():
        return given
    if top in sys.modules or importlib.util.find_spec(top) is not None:  # a top-level name: finding imports nothing
        return None
    spec = importlib.machinery.PathFinder.find_spec(top, [os.getcwd()])
    return spec.origin if spec is not None and spec.has_location else None


@contextmanager
def importing(module_name: str) -> Iterator[None]:
    """The block's import of `module_name` takes its top-level module from `_file_of` (and
    remembers that file for the processes started later); nothing else changes."""
    top = module_name.partition(".")[0]
    file = _file_of(top)
    if file is None:
        yield
        return
    finder = _OneName(top, file)
    sys.meta_path.insert(0, finder)
    try:
        yield
    finally:
        sys.meta_path.remove(finder)
    if sys.modules.get(top) is not None and getattr(sys.modules[top], "__file__", None) == file:
        os.environ[USER_FILES_ENV] = json.dumps({**user_files(), top: file})


@contextmanager
def no_folder_on_path() -> Iterator[None]:
    """Processes started in the block (a worker pool, submitit's tasks) do not put the current
    folder on their path: spawn runs ``python -c``, submitit ``python -m``, both of which would."""
    before = os.environ.get("PYTHONSAFEPATH")
    os.environ["PYTHONSAFEPATH"] = "1"
    try:
        yield
    finally:
        if before is None:
            os.environ.pop("PYTHONSAFEPATH", None)
        else:
            os.environ["PYTHONSAFEPATH"] = before
