"""Folders the toolkit makes and removes (spills, drawings, a reconstruction's products, an
archive's unpacking), never through a link: the one place such a folder is removed or made anew."""

from __future__ import annotations

import shutil
from pathlib import Path

from e3cm_bench.ground.files import refuse_link


def remove_folder(path: str | Path, ignore_errors: bool = False, what: str = "e3cm-bench makes it") -> None:
    """Remove a folder the toolkit made (a spill, drawings, a reconstruction's products) with all
    it holds, never through a link: a link at `path` is refused in one line (refuse_link), neither
    followed nor removed, and so is a file; shutil.rmtree removes a link inside the folder, never
    its target. Nothing at `path`: nothing done. ignore_errors: an OS error on the way is ignored
    (a cleanup), a link still refused. what: the folder's use, said where a file is in its place.
    (shutil.rmtree(ignore_errors=True) alone skips a link in silence, and whatever then makes
    the folder again makes it in the link's target: issue 81.)"""
    path = refuse_link(path)
    if not path.exists():
        return
    if not path.is_dir():
        raise ValueError(f"{path}: is not a folder ({what}); move it away and rerun")
    shutil.rmtree(path, ignore_errors=ignore_errors)


def fresh_folder(path: str | Path, what: str = "e3cm-bench makes it") -> Path:
    """An empty folder made anew at `path`, never through a link: what an earlier run left there
    is removed (remove_folder: a link or a file refused), and the folder is made without exist_ok,
    so that a link planted between is an error rather than a folder to write into (a link above
    `path`, in a folder the user named, is the user's)."""
    path = Path(path)
    remove_folder(path, what=what)
    path.mkdir(parents=True)
    return path
