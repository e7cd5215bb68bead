"""The documentation: the strict MkDocs build, tables rendered from the CSVs that
hold them, runnable examples run as written, and the README's headline table against its CSV."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

REPO = Path(__file__).resolve().parents[1]
RUNNABLE = re.compile(r"<!-- runnable -->\n```python\n(.*?)```", re.S)
# What a runnable block prints, where the page shows it: the next ```text block marked prints
# (before the next runnable block); its lines must come out in this order.
PRINTS = re.compile(r"(?:(?!<!-- runnable -->).)*?<!-- prints -->\n```text\n(.*?)```", re.S)


def runnable_blocks() -> list[tuple[str, int, str]]:
    """(page, index, code) of every fenced block marked runnable in docs/*.md; the Python API
    page's is run by tests/test_api.py, with its own checks."""
    blocks = []
    for page in sorted((REPO / "docs").glob("*.md")):
        for index, match in enumerate(RUNNABLE.finditer(page.read_text())):
            blocks.append((page.name, index, match.group(1)))
    return blocks


def printed_lines(page: str, index: int) -> list[str] | None:
    """The lines the page says its index-th runnable block prints, or None where it shows none."""
    text = (REPO / "docs" / page).read_text()
    block = list(RUNNABLE.finditer(text))[index]
    shown = PRINTS.match(text, block.end())
    return shown.group(1).splitlines() if shown else None


def test_there_are_runnable_examples_and_the_api_page_has_one():
    pages = [page for page, _, _ in runnable_blocks()]
    assert "api.md" in pages and len(pages) >= 2


# Pages whose every Python block shows code to run, so every one is marked runnable.
FULLY_RUNNABLE = ("own-matcher.md", "architecture.md")


def test_every_python_block_of_the_fully_runnable_pages_is_marked():
    for name in FULLY_RUNNABLE:
        text = (REPO / "docs" / name).read_text()
        blocks = text.count("```python\n")
        assert blocks and len(RUNNABLE.findall(text)) == blocks, f"{name}: a ```python block is not marked runnable"


# interchange.md's first block (an hloc export and its import, end to end): 23 s in the fast set under a
# load of about 7 on the shared 2-core machine (docs/development.md, Testing)
SLOW_BLOCKS = {("interchange.md", 0)}


@pytest.mark.parametrize("page, index, code", [pytest.param(*b, marks=pytest.mark.slow) if b[:2] in SLOW_BLOCKS else b
                                               for b in runnable_blocks() if b[0] != "api.md"],
                         ids=lambda v: v if isinstance(v, str) and v.endswith(".md") else None)
def test_runnable_examples_run_as_written(page, index, code, request, tmp_path):
    work = tmp_path / "checkout"  # a checkout-like folder: ../shared/data and runs/ resolve here
    work.mkdir()
    if "../shared" in code:  # only the blocks that read the real samples skip without them
        (tmp_path / "shared").symlink_to(request.getfixturevalue("shared_data").parent)
    done = subprocess.run([sys.executable, "-c", code], cwd=work, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, f"{page} block {index}:\n{done.stderr[-2000:]}"
    # what it prints is what the page shows, line for line and in order (other lines may come
    # between: progress, tables); a block that shows no output asserts what it made instead
    expected = printed_lines(page, index)
    if expected is None:
        assert re.search(r"^\s*assert ", code, re.M), f"{page} block {index}: shows no output and asserts nothing"
        return
    lines, at = done.stdout.splitlines(), 0
    for line in expected:
        found = next((k for k in range(at, len(lines)) if lines[k].rstrip() == line.rstrip()), None)
        assert found is not None, f"{page} block {index}: does not print {line!r} (after line {at}):\n{done.stdout[-2000:]}"
        at = found + 1


def test_readme_headline_table_is_the_csvs():
    """Every row of the README's headline table equals results/sample/table1_hpatches/table.csv
    (rounded as shown), each number with its interval, so the README cannot drift from the run either."""
    text = (REPO / "README.md").read_text()
    section = text.split("## Headline")[1].split("\n## ")[0]
    rows = [line for line in section.splitlines() if line.startswith("| ") and not line.startswith("| method")]
    table = pd.read_csv(REPO / "results/sample/table1_hpatches/table.csv").query("source == 'measured'").set_index("method")
    assert len(rows) == len(table) == 7
    for row in rows:
        method, *values = [cell.strip() for cell in row.strip("|").split("|")]
        expected = [f"{table.loc[method, c]:.2f} [{table.loc[method, c + '_lo']:.2f}, {table.loc[method, c + '_hi']:.2f}]"
                    for c in ("h_acc@1", "h_acc@3", "h_acc@5", "mma@3")]
        assert values == expected, (method, values, expected)


def mkdocs_build(root: Path, site: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(root / "mkdocs.yml"), "-d", str(site)],
                          capture_output=True, text=True, timeout=600, env={**__import__("os").environ, "NO_MKDOCS_2_WARNING": "1"})


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    pytest.importorskip("mkdocs", reason="the docs extra (mkdocs) is not installed")
    pytest.importorskip("mkdocstrings", reason="the docs extra (mkdocstrings) is not installed")
    site = tmp_path_factory.mktemp("site")
    built = mkdocs_build(REPO, site)
    assert built.returncode == 0, built.stderr[-3000:]
    return site


def test_the_strict_build_has_every_page_the_cli_and_api_references(site):
    pages = ["getting-started", "data", "benchmarks", "methods", "peers", "own-matcher", "results", "report", "speed",
             "robustness", "calibration", "cluster", "cli", "api", "development", "architecture"]
    for page in pages:
        assert (site / page / "index.html").is_file(), page
    architecture = (site / "architecture" / "index.html").read_text()  # the layer table, computed at build time
    assert re.search(r"\d+ modules in \d+ layers", architecture) and "<code>storage.folder</code>" in architecture
    assert "<code>storage/</code>" in architecture and "0 import(s) from a package to one after it" in architecture
    cli = (site / "cli" / "index.html").read_text()
    for command in ("e3cm-bench hpatches", "e3cm-bench download", "e3cm-bench datasets", "--pose-estimator"):
        assert command in cli, command
    api = (site / "api" / "index.html").read_text()
    assert "run_benchmark" in api and "MatcherEntry" in api and "weights_beside" in api
    assert (site / "results" / "perf" / "scaling.png").is_file()  # figures come from results/ as the runs wrote them


def test_no_measured_table_is_retyped(site):
    """Every table a page renders from a CSV says so, and no page holds the old hand-typed
    sample table any more."""
    results = (site / "results" / "index.html").read_text()
    for path in ("results/sample/table1_hpatches/table.csv", "results/baselines/demo_hpatches.csv"):
        assert f"Rendered at build time from <code>{path}</code>" in results
    for page in (REPO / "docs").glob("*.md"):
        assert "| e3cm-plus [efficientnet_lite0]    | measured |" not in page.read_text(), page


def test_a_changed_csv_changes_the_rendered_page(site, tmp_path):
    """A copy of the repository's docs with one CSV edited: the page built from it shows the
    edit (the build reads the CSV; nothing is cached or retyped)."""
    copy = tmp_path / "repo"
    copy.mkdir()
    # scripts and pyproject.toml: the layer table (code_shape finds the checkout by its pyproject.toml)
    for name in ("mkdocs.yml", "pyproject.toml", "docs", "results", "e3cm_bench", "scripts"):
        source = REPO / name
        (shutil.copytree if source.is_dir() else shutil.copy)(source, copy / name)
    csv = copy / "results/sample/table1_hpatches/table.csv"
    table = pd.read_csv(csv)
    row = (table["method"] == "sift") & (table["source"] == "measured")
    table.loc[row, "method"] = "sift-edited"
    table.loc[row, "h_acc@1"] = 0.777
    table.to_csv(csv, index=False)
    before = (site / "results" / "index.html").read_text()
    built = mkdocs_build(copy, tmp_path / "site")
    assert built.returncode == 0, built.stderr[-3000:]
    after = (tmp_path / "site" / "results" / "index.html").read_text()
    # the edited number, shown with the interval the CSV still holds for the row
    cells = r"sift-edited</td>\s*<td[^>]*>measured</td>\s*<td[^>]*>0\.78 \[0\.53, 0\.93\]</td>"
    assert re.search(cells, after) and not re.search(cells, before)
