"""The package as installed: the paper's experiment configs and numbers ship
as package data under e3cm_bench/paper/, found through importlib.resources; `reproduce` takes a
config by name; a wheel installed away from the checkout finds them. (.ci/run installs the wheel
into a clean virtual environment and runs demo, reproduce and report from it.)"""

from __future__ import annotations

import html
import os
import shutil
import subprocess
import sys
import zipfile
from importlib import resources
from pathlib import Path

import pandas as pd
import pytest

from e3cm_bench.reporting import tables as report
from e3cm_bench.benchmarks import BENCHMARKS
from e3cm_bench.pipeline.experiments import load_experiment
from e3cm_bench.paper import CONFIG_DIR, PAPER_DIR, config_names, resolve_config
from helpers import flat, invoke, one_line_error

REPO = Path(__file__).resolve().parents[1]
PAPER_NAMES = ("table1", "table2", "table3", "fig5")


def shipped_files() -> list[str]:
    """Every file of e3cm_bench/paper/ as a wheel names it."""
    return sorted(p.relative_to(REPO).as_posix() for p in PAPER_DIR.rglob("*")
                  if p.is_file() and "__pycache__" not in p.parts)


def test_the_paper_data_is_found_through_importlib_resources():
    data = resources.files("e3cm_bench.paper")
    configs = sorted(entry.name for entry in data.joinpath("configs").iterdir() if entry.name.endswith(".yaml"))
    assert "table1_hpatches.yaml" in configs and configs == sorted(p.name for p in CONFIG_DIR.glob("*.yaml"))
    with_tables = [b for b in BENCHMARKS.values() if b.paper_table]
    assert {b.paper_table for b in with_tables} >= {"table1.csv", "table2.csv", "table3.csv"}
    for benchmark in with_tables:
        reference = report.paper_reference(benchmark)
        assert reference.is_file() and reference.read_text() == data.joinpath(benchmark.paper_table).read_text()
    # the top of the checkout keeps only the locks; a second copy of the configs would drift
    assert sorted(p.name for p in (REPO / "configs").iterdir()) == ["constraints-cpu.txt", "constraints.txt"]
    assert not list((REPO / "results").glob("paper/*"))


@pytest.mark.slow  # 89 s alone on a loaded 2-core machine (docs/development.md, Testing)
def test_every_shipped_config_resolves_by_name_and_is_valid():
    names = config_names()
    # the short names first: the paper's, and WxBS and EVD (every built-in benchmark)
    assert list(names)[:6] == sorted((*PAPER_NAMES, "wxbs", "evd")) and names["table1"] == CONFIG_DIR / "table1_hpatches.yaml"
    assert names["wxbs"] == CONFIG_DIR / "wxbs_all.yaml" and names["evd"] == CONFIG_DIR / "evd_all.yaml"
    # a prefix several configs share names none of them
    assert "design" not in names and "refine" not in names and "e3cm" not in names
    for name, path in names.items():
        assert resolve_config(name) == path
        assert load_experiment(resolve_config(name))["methods"]
    assert resolve_config(CONFIG_DIR / "table1_hpatches.yaml") == resolve_config("table1")  # the path form stays


def test_a_file_of_ones_own_wins_over_a_shipped_name(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    Path("table1").write_text("benchmark: hpatches\nmethods: [{matcher: sift}]\n")
    assert resolve_config("table1") == Path("table1")


def test_an_unknown_name_is_one_line_listing_the_known_ones(tmp_path):
    line = one_line_error(invoke("reproduce", "tabel1", "--out", tmp_path / "o"))
    assert line.startswith("error: tabel1: no such experiment config file, nor a known name (")
    assert all(name in line for name in config_names())
    assert not (tmp_path / "o").exists()
    usage = flat(invoke("reproduce", "--help").output)
    assert all(name in usage for name in (*PAPER_NAMES, "table1_hpatches", "refine_ablation_kitti"))


@pytest.mark.slow  # 56 s alone on a loaded 2-core machine (docs/development.md, Testing)
def test_reproduce_by_name_from_another_folder(tmp_path, monkeypatch, shared_data):
    monkeypatch.chdir(tmp_path)  # nothing is read relative to the checkout
    result = invoke("reproduce", "table1", "--root", shared_data / "hpatches-sequences-release", "--methods", "sift",
                    "--limit", 1, "--max-side", 320, "--out", "t1")
    assert result.exit_code == 0, result.output
    table = pd.read_csv(tmp_path / "t1" / "table.csv")
    paper = pd.read_csv(PAPER_DIR / "table1.csv")
    assert list(table.loc[table["source"] == "paper", "method"]) == list(paper["method"])
    assert list(table.loc[table["source"] == "measured", "method"]) == ["sift"]
    assert (tmp_path / "t1" / "experiment.yaml").read_text().startswith("name: table1_hpatches\n")


@pytest.mark.slow  # 60 s alone on a loaded 2-core machine (docs/development.md, Testing)
def test_a_wheel_installed_away_from_the_checkout_reports_the_paper_rows(tmp_path):
    """The wheel, built from the package as it is on disk and installed into a folder of its own,
    imported ahead of the editable install from a folder outside the checkout: its report of a
    committed sample run holds every row of the paper's Table 1."""
    source = tmp_path / "source"
    shutil.copytree(REPO / "e3cm_bench", source / "e3cm_bench", ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, source / name)
    # built as pip builds it for a user (an isolated build environment with pyproject.toml's
    # setuptools): the test environment's own setuptools may be older than the build needs
    build = [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(tmp_path / "dist"), str(source)]
    subprocess.run(build, check=True, capture_output=True, timeout=300)
    wheel, = (tmp_path / "dist").glob("e3cm_bench-*.whl")
    missing = set(shipped_files()) - set(zipfile.ZipFile(wheel).namelist())
    assert not missing, f"not in the wheel: {sorted(missing)}"

    site = tmp_path / "site"
    install = [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(site), str(wheel)]
    subprocess.run(install, check=True, capture_output=True, timeout=300)
    away = tmp_path / "away"
    shutil.copytree(REPO / "results" / "sample" / "table1_hpatches" / "sift", away / "sift")
    env = {**os.environ, "PYTHONPATH": str(site)}
    where = subprocess.run([sys.executable, "-c", "import e3cm_bench.paper as p; print(p.resolve_config('table1'))"],
                           cwd=away, env=env, capture_output=True, text=True, check=True)
    assert Path(where.stdout.strip()) == site / "e3cm_bench" / "paper" / "configs" / "table1_hpatches.yaml"
    done = subprocess.run([sys.executable, "-m", "e3cm_bench.cli", "report", "sift", "--out", "site"],
                          cwd=away, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    page = (away / "site" / "index.html").read_text()
    paper = pd.read_csv(PAPER_DIR / "table1.csv")["method"]
    assert all(f'<tr class="paper"><td class="t">{html.escape(m)}</td>' in page for m in paper)
    assert page.count('<tr class="paper">') == len(paper)


CUDA_ONLY = ("cuda-", "nvidia-", "triton==")  # torch's CUDA build's own packages (PyPI's torch)


def _pins(path: Path) -> list[str]:
    return [line for line in path.read_text().splitlines() if line and not line.startswith("#")]


def test_the_cpu_lock_is_the_lock_without_cuda():
    """configs/constraints-cpu.txt (the README's line for a machine without a GPU): every pin of
    the lock but the CUDA libraries, torch and torchvision as their CPU builds of the same version."""
    lock, cpu = _pins(REPO / "configs" / "constraints.txt"), _pins(REPO / "configs" / "constraints-cpu.txt")
    cuda = [pin for pin in lock if pin.startswith(CUDA_ONLY)]
    assert len(cuda) >= 10 and not [pin for pin in cpu if pin.startswith(CUDA_ONLY)]
    expected = [pin + "+cpu" if pin.split("==")[0] in ("torch", "torchvision") else pin
                for pin in lock if pin not in cuda]
    assert cpu == expected
    assert "torch==2.14.1+cpu" in cpu


def test_the_readme_installs_the_cpu_lock_from_pytorchs_index():
    readme = (REPO / "README.md").read_text()
    line = next(line for line in readme.splitlines() if line.startswith("# No GPU?"))
    command = line.split(": ", 1)[1]
    assert "-c configs/constraints-cpu.txt" in command and "--extra-index-url https://download.pytorch.org/whl/cpu" in command


def test_the_readme_says_beside_the_cpu_line_what_it_needs_and_what_to_do_without_it():
    """Round eight: the line failed after 17 s with a resolver error where PyTorch's index could not be
    reached, and nothing said so. The comment under it names the index, the error and the way round."""
    lines = (REPO / "README.md").read_text().splitlines()
    k = next(k for k, line in enumerate(lines) if line.startswith("# No GPU?"))
    beside = lines[k + 1]
    assert beside.startswith("#") and "https://download.pytorch.org/whl/cpu" in beside
    assert "ResolutionImpossible" in beside and "use the next line instead" in beside
    assert not lines[k + 2].startswith("#")  # the next line is the command it names
