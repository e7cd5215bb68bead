"""`e3cm-bench check`: the environment recorded in a baseline, and per-method tolerance files.

Runs here are written by hand (config.yaml + summary.csv, what `check` reads), so no model runs.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest
import yaml

from e3cm_bench.gate import check
from e3cm_bench.storage.environment import parse_environment
from e3cm_bench.ground.machine import run_environment
from helpers import flat, invoke, one_line_error

VERSIONS = {"python": "3.12.3", "e3cm-bench": "0.1.0", "torch": "2.14.1", "torchvision": "0.29.1", "numpy": "2.4.6",
            "opencv-python-headless": "5.0.0.93", "h5py": "3.16.0", "pandas": "3.1.1"}
ENVIRONMENT = {"torch": "2.14.1+cu130", "cpu_capability": "AVX512", "threads": 2, "cpu_model": "Intel(R) Xeon(R) Processor",
               "cpu_flags": {"avx512_bf16": True, "avx512f": True, "avx2": True}}
ENVIRONMENT_STRING = ("python=3.12.3; torch=2.14.1+cu130; torchvision=0.29.1; numpy=2.4.6; "
                      "opencv-python-headless=5.0.0.93; cpu=AVX512; threads=2")
NOTE = "environment differs from the baseline's:"


def write_run(folder: Path, method: str, h_acc1: float = 0.6, versions: dict | None = VERSIONS,
              environment: dict | None = ENVIRONMENT) -> Path:
    """A finished hpatches run as `check` sees it."""
    folder.mkdir(parents=True, exist_ok=True)
    config = {"benchmark": "hpatches", "method": method}
    if versions is not None:
        config["versions"] = dict(versions)
    if environment is not None:
        config["environment"] = dict(environment)
    (folder / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    summary = {"n_pairs": 15, "n_matches": 800.0, **{f"mma@{t}": min(1.0, 0.3 + 0.07 * t) for t in range(1, 11)},
               "h_acc@1": h_acc1, "h_acc@3": 0.8, "h_acc@5": 0.9}
    pd.DataFrame([summary]).to_csv(folder / "summary.csv", index=False)
    return folder


def edit_config(folder: Path, **changes) -> None:
    """Change config.yaml: versions=/environment= dicts are merged in; None removes the key."""
    path = folder / "config.yaml"
    config = yaml.safe_load(path.read_text())
    for key, value in changes.items():
        if value is None:
            config.pop(key, None)
        else:
            config[key] = {**config.get(key, {}), **value}
    path.write_text(yaml.safe_dump(config, sort_keys=False))


@pytest.fixture
def runs(tmp_path) -> tuple[Path, Path]:
    """Runs of methods a and b, and a baseline written from them by check --update."""
    root = tmp_path / "runs"
    write_run(root / "a", "a")
    write_run(root / "b", "b")
    baseline = tmp_path / "baseline.csv"
    result = invoke("check", root, "--baseline", baseline, "--update")
    assert result.exit_code == 0 and "2 runs written" in flat(result.output)
    return root, baseline


def notes_in(output: str) -> list[str]:
    """The environment notes, each one logical line (check wraps them at the console's width,
    80 columns in a log)."""
    notes, current = [], None
    for line in output.splitlines():
        if line.startswith(NOTE):
            current = len(notes)
            notes.append(line.rstrip())
        elif current is not None and line.strip() and not line.startswith(("check:", "regression:", "improvement:",
                                                                             "problem:", "moved:", "noise model:")):
            notes[current] += " " + line.strip()
        else:
            current = None
    return notes


# --------------------------------------------------------------------------- environment


def test_run_environment_names_what_numbers_depend_on(monkeypatch):
    import torch

    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "AVX2")
    monkeypatch.delenv("ATEN_CPU_CAPABILITY", raising=False)
    environment = run_environment()
    assert environment["torch"] == torch.__version__
    assert environment["cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    assert environment["threads"] == torch.get_num_threads()
    assert environment["ONEDNN_MAX_CPU_ISA"] == "AVX2" and "ATEN_CPU_CAPABILITY" not in environment
    assert environment["cpu_model"]
    if Path("/proc/cpuinfo").is_file():
        assert set(environment["cpu_flags"]) == {"avx512_bf16", "amx_bf16", "avx512f", "avx2"}
    yaml.safe_load(yaml.safe_dump(environment))  # plain YAML values


def test_update_writes_the_environment_and_check_reads_it_back(runs, tmp_path):
    root, baseline = runs
    table = pd.read_csv(baseline)
    assert list(table.columns) == ["benchmark", "method", "h_acc@1", "h_acc@3", "h_acc@5", "mma@3", "environment",
                                   "identity", "protocol_items"]
    assert list(table["environment"]) == [ENVIRONMENT_STRING] * 2
    assert parse_environment(ENVIRONMENT_STRING) == {
        "python": "3.12.3", "torch": "2.14.1+cu130", "torchvision": "0.29.1", "numpy": "2.4.6",
        "opencv-python-headless": "5.0.0.93", "cpu": "AVX512", "threads": "2"}
    # The same environment: nothing to say, and the column is no metric (8 metrics, not 10).
    report = tmp_path / "summary.md"
    result = invoke("check", root, "--baseline", baseline, "--summary", report)
    assert result.exit_code == 0 and "no regression" in flat(result.output) and NOTE not in result.output
    assert "8 metrics checked: 0 regression(s)" in report.read_text() and "environment" not in report.read_text()


def test_a_different_environment_is_one_line_and_no_failure(runs, tmp_path):
    root, baseline = runs
    for method in ("a", "b"):
        edit_config(root / method, versions={"torch": "2.15.0"},
                    environment={"torch": "2.15.0+cpu", "cpu_capability": "AVX2", "ONEDNN_MAX_CPU_ISA": "AVX2"})
    report = tmp_path / "summary.md"
    result = invoke("check", root, "--baseline", baseline, "--summary", report)
    assert result.exit_code == 0 and "no regression" in flat(result.output)
    line = f"{NOTE} torch 2.14.1+cu130 -> 2.15.0+cpu, cpu AVX512 -> AVX2, ONEDNN_MAX_CPU_ISA unset -> AVX2"
    assert notes_in(result.output) == [line]  # one note for both runs
    assert f"- {line}\n" in report.read_text()

    # A difference of one run only names that run; runs that differ alike share a line.
    edit_config(root / "b", environment={"threads": 1})
    result = invoke("check", root, "--baseline", baseline)
    assert result.exit_code == 0
    assert sorted(notes_in(result.output)) == [f"{line} (a on hpatches)", f"{line}, threads 2 -> 1 (b on hpatches)"]


def test_environments_missing_on_either_side(runs, tmp_path):
    root, baseline = runs
    # A run from before the environment was recorded: compared on its packages only.
    edit_config(root / "a", environment=None, versions={"numpy": "2.5.0"})
    edit_config(root / "b", environment=None)
    result = invoke("check", root, "--baseline", baseline)
    assert result.exit_code == 0
    # Their torch is the package metadata's 2.14.1, without the build tag: not a difference.
    assert notes_in(result.output) == [f"{NOTE} numpy 2.4.6 -> 2.5.0 (a on hpatches)"]
    # A baseline without the column (written before it existed) checks as before, silently.
    pd.read_csv(baseline).drop(columns=["environment"]).to_csv(baseline, index=False)
    result = invoke("check", root, "--baseline", baseline)
    assert result.exit_code == 0 and NOTE not in result.output
    # An empty or hand-edited cell is no error either.
    table = pd.read_csv(baseline)
    table["environment"] = ["", "torch 2.14; cpu=AVX512; nonsense"]
    table.to_csv(baseline, index=False)
    assert parse_environment(float("nan")) == {} and parse_environment("x; cpu=AVX2;=1") == {"cpu": "AVX2"}
    result = invoke("check", root, "--baseline", baseline)
    assert result.exit_code == 0 and NOTE not in result.output


# --------------------------------------------------------------------------- tolerances


def write_tolerances(path: Path, rows: list[tuple], header=("benchmark", "method", "metric", "tolerance", "spread")) -> Path:
    lines = [",".join(header)] + [",".join(str(v) for v in row) for row in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture
def dropped(runs) -> tuple[Path, Path]:
    """a and b both lost 0.2 of h_acc@1 (default tolerance 0.07)."""
    root, baseline = runs
    write_run(root / "a", "a", h_acc1=0.4)
    write_run(root / "b", "b", h_acc1=0.4)
    return root, baseline


def regressions(output: str) -> list[str]:
    return sorted(line.split(":")[1].strip() for line in output.splitlines() if line.startswith("regression:"))


def test_per_method_tolerances_from_a_file(dropped, tmp_path):
    root, baseline = dropped
    assert regressions(invoke("check", root, "--baseline", baseline).output) == ["a on hpatches", "b on hpatches"]
    # A large tolerance for a alone: a passes, b fails with the default.
    tolerances = write_tolerances(tmp_path / "tol.csv", [("hpatches", "a", "h_acc@1", 0.25, 0.1)])
    report = tmp_path / "summary.md"
    result = invoke("check", root, "--baseline", baseline, "--tolerances", tolerances, "--summary", report)
    assert result.exit_code == 1 and regressions(result.output) == ["b on hpatches"]
    assert "| hpatches | a | h_acc@1 | 0.6000 | 0.4000 | -0.2000 | 0.25 | ok |" in report.read_text()
    assert "| hpatches | b | h_acc@1 | 0.6000 | 0.4000 | -0.2000 | 0.07 | **regression** |" in report.read_text()
    # The most specific row wins: exact > method with * > * *.
    tolerances = write_tolerances(tmp_path / "tol.csv", [
        ("*", "*", "h_acc@1", 0.3, ""), ("*", "b", "h_acc@1", 0.01, ""), ("hpatches", "a", "h_acc@1", 0.01, ""),
        ("*", "a", "h_acc@1", 0.5, ""), ("yfcc", "b", "h_acc@1", 0.5, "")])
    result = invoke("check", root, "--baseline", baseline, "--tolerances", tolerances)
    assert result.exit_code == 1 and regressions(result.output) == ["a on hpatches", "b on hpatches"]
    tolerances = write_tolerances(tmp_path / "tol.csv", [("*", "*", "h_acc@1", 0.3, ""), ("*", "b", "h_acc@1", 0.01, "")])
    result = invoke("check", root, "--baseline", baseline, "--tolerances", tolerances)
    assert result.exit_code == 1 and regressions(result.output) == ["b on hpatches"]


def test_the_command_line_wins_over_the_file(dropped, tmp_path):
    root, baseline = dropped
    tolerances = write_tolerances(tmp_path / "tol.csv", [("hpatches", "a", "h_acc@1", 0.25, ""), ("*", "*", "h_acc@1", 0.01, "")])
    # For one method ...
    result = invoke("check", root, "--baseline", baseline, "--tolerances", tolerances, "--tolerance", "a:h_acc@1=0.1")
    assert result.exit_code == 1 and regressions(result.output) == ["a on hpatches", "b on hpatches"]
    result = invoke("check", root, "--baseline", baseline, "--tolerances", tolerances, "--tolerance", "b:h_acc@1=0.3")
    assert result.exit_code == 0
    # ... for all; a per-method one beats it.
    result = invoke("check", root, "--baseline", baseline, "--tolerances", tolerances, "--tolerance", "h_acc@1=0.3")
    assert result.exit_code == 0
    result = invoke("check", root, "--baseline", baseline, "--tolerance", "h_acc@1=0.3", "--tolerance", "b:h_acc@1=0.1")
    assert result.exit_code == 1 and regressions(result.output) == ["b on hpatches"]


def test_tolerances_precedence_in_code():
    limits = check.Tolerances(rows={("*", "*", "auc@5"): 1.0, ("yfcc", "*", "auc@5"): 2.0, ("*", "m", "auc@5"): 3.0,
                                    ("yfcc", "m", "auc@5"): 4.0},
                              options={(None, "P"): 0.5, ("m", "P"): 0.6})
    assert limits.get("yfcc", "m", "auc@5") == 4.0 and limits.get("megadepth", "m", "auc@5") == 3.0
    assert limits.get("yfcc", "n", "auc@5") == 2.0 and limits.get("megadepth", "n", "auc@5") == 1.0
    assert limits.get("yfcc", "m", "P") == 0.6 and limits.get("yfcc", "n", "P") == 0.5
    assert limits.get("yfcc", "n", "auc@10") == check.DEFAULT_TOLERANCES["auc@10"]
    # The method is more specific than the benchmark: (*, method) > (benchmark, *).
    assert check.Tolerances(rows={("yfcc", "*", "auc@5"): 2.0, ("*", "m", "auc@5"): 3.0}).get("yfcc", "m", "auc@5") == 3.0
    assert limits.get("yfcc", "n", "unknown") is None
    assert check.parse_tolerances(["auc@10=2.5"]) == {**check.DEFAULT_TOLERANCES, "auc@10": 2.5}


@pytest.mark.parametrize("rows, header, expected", [
    ([("hpatches", "a", "h_acc@1", "nan")], None, "finite number >= 0"),
    ([("hpatches", "a", "h_acc@1", "")], None, "finite number >= 0"),
    ([("hpatches", "a", "h_acc@1", "-0.1")], None, "finite number >= 0"),
    ([("hpatches", "a", "h_acc@1", "inf")], None, "finite number >= 0"),
    ([("hpatches", "a", "h_acc@1", "wide")], None, "not a number"),
    ([("hpatches", "a", "h_acc@1", "0.1"), ("hpatches", "a", "h_acc@1", "0.2")], None, "also on line 2"),
    ([("hpatches", "", "h_acc@1", "0.1")], None, "empty method"),
    ([("hpatches", "a", "0.1")], ("benchmark", "method", "tolerance"), "missing column(s) metric"),
])
def test_a_broken_tolerance_file_is_refused(dropped, tmp_path, rows, header, expected):
    root, baseline = dropped
    path = tmp_path / "broken-tol.csv"
    if header is None:
        write_tolerances(path, rows, header=("benchmark", "method", "metric", "tolerance"))
    else:
        write_tolerances(path, rows, header=header)
    line = one_line_error(invoke("check", root, "--baseline", baseline, "--tolerances", path))
    assert "broken-tol.csv" in line and expected in line


def test_a_broken_command_line_tolerance_is_refused(runs, tmp_path):
    root, baseline = runs
    for item in ("h_acc@1=nan", "a:h_acc@1=-1", "h_acc@1=inf"):
        line = one_line_error(invoke("check", root, "--baseline", baseline, "--tolerance", item))
        assert item in line and "finite number >= 0" in line
    for item in ("h_acc@1", ":h_acc@1=0.1", "h_acc@1=wide"):
        assert "METRIC=VALUE" in one_line_error(invoke("check", root, "--baseline", baseline, "--tolerance", item))
    line = one_line_error(invoke("check", root, "--baseline", baseline, "--tolerances", tmp_path / "none.csv"))
    assert "none.csv" in line and "tolerance file" in line
