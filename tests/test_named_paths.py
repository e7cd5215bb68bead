"""Every `scripts/...` and `tests/...` path the documentation, the README and CI's script name
exists in the checkout (a glob matches at least one file), so a moved or renamed script or test
file cannot leave a stale reference behind."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# A path starts at scripts/ or tests/ (not inside a URL or another path) and runs over
# name characters, slashes, globs and {a,b} alternatives; a trailing dot or comma is prose.
NAMED = re.compile(r"(?<![\w/.-])(?:scripts|tests)/[\w./*{},-]*")
READERS = sorted((REPO / "docs").glob("*.md")) + [REPO / "docs" / "hooks.py", REPO / "README.md", REPO / ".ci" / "run"]


def expand(path: str) -> list[str]:
    """`a_{x,y}.csv` -> [`a_x.csv`, `a_y.csv`] (one level of braces, as the docs write them)."""
    match = re.search(r"\{([^{}]*)\}", path)
    if match is None:
        return [path]
    return [p for alt in match.group(1).split(",") for p in expand(path[:match.start()] + alt + path[match.end():])]


def named_paths(text: str) -> list[str]:
    found = []
    for match in NAMED.finditer(text):
        path = match.group(0).rstrip(".,")
        if path.count("{") != path.count("}"):  # a brace closed after the match: take what precedes it
            path = path[:path.index("{")]
        found += expand(path)
    return found


def missing(path: str) -> bool:
    if any(c in path for c in "*?["):
        return not any(REPO.glob(path))
    return not (REPO / path).exists()


@pytest.mark.parametrize("reader", READERS, ids=lambda p: str(p.relative_to(REPO)))
def test_every_script_and_test_path_named_exists(reader):
    paths = named_paths(reader.read_text())
    gone = sorted({p for p in paths if missing(p)})
    assert not gone, f"{reader.relative_to(REPO)} names paths that do not exist: {', '.join(gone)}"


def test_the_reader_finds_paths_as_the_docs_write_them():
    text = ("Run `python scripts/measure/pair_speed.py --json`, then tests/test_x*.py; see "
            "https://github.com/o/r/tree/main/tests/data and results/perf/a_{fp32,bf16}.txt or scripts/slurm/.")
    assert named_paths(text) == ["scripts/measure/pair_speed.py", "tests/test_x*.py", "scripts/slurm/"]
    assert expand("tests/a_{b,c}.py") == ["tests/a_b.py", "tests/a_c.py"]
    assert missing("scripts/no_such_script.py") and not missing("scripts/slurm/array.sh")
    assert missing("tests/no_such_*.py") and not missing("tests/*/test_speed.py")


def test_every_test_module_name_is_unique_across_the_folders():
    """pytest imports a test module in a folder without __init__.py by its bare name: two
    test_x.py in two subject folders would collide."""
    names = [p.name for p in (REPO / "tests").rglob("test_*.py") if "data" not in p.relative_to(REPO / "tests").parts]
    assert len(names) == len(set(names)), sorted({n for n in names if names.count(n) > 1})
