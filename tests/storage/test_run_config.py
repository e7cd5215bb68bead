"""A run's config.yaml: RunConfig its one reader (one line naming the file for a bad one),
load_run_pairs the one reload of a run's pairs, and no other module reading the file."""

from __future__ import annotations

import ast
from pathlib import Path

import pandas as pd
import pytest
import yaml

from e3cm_bench.benchmarks.from_record import dataset_source, evaluation_of, load_run_pairs
from e3cm_bench.storage import RunConfig, RunFolder
from helpers import invoke

REPO = Path(__file__).resolve().parents[2]
# What the one-reader scan reads: the package and the scripts (scripts/results/ reads runs too).
SCANNED = ("e3cm_bench", "scripts")


# --------------------------------------------------------------------------- a bad config.yaml


@pytest.mark.parametrize("text, problem", [
    (None, "not found"),
    ("benchmark: [hpatches\n", "not valid YAML"),
    ("- just\n- a list\n", "expected a mapping"),
    ("method: sift\nidentity: {matcher: sift}\n", "records no benchmark"),
])
def test_a_bad_config_is_one_line_naming_the_file(tmp_path, text, problem):
    path = tmp_path / "config.yaml"
    if text is not None:
        path.write_text(text)
    for read in (RunConfig.read, lambda p: RunFolder(p.parent).run_config(), load_run_pairs):
        with pytest.raises(ValueError) as error:
            read(path)
        message = str(error.value)
        assert "\n" not in message and message.startswith(str(path)) and problem in message


def test_a_config_of_an_unknown_benchmark_or_without_a_dataset_is_named(tmp_path):
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump({"benchmark": "no-such-benchmark", "method": "x", "identity": None}))
    with pytest.raises(ValueError, match=r"^" + str(path).replace("\\", r"\\") + ": ") as error:
        load_run_pairs(tmp_path)
    assert "no-such-benchmark" in str(error.value)
    path.write_text(yaml.safe_dump({"benchmark": "hpatches", "method": "x", "identity": None}))
    with pytest.raises(ValueError, match="records no dataset root") as error:
        load_run_pairs(tmp_path)
    assert str(path) in str(error.value)


def test_the_folder_record_keeps_the_keys_of_older_versions(tmp_path):
    """One reader, one type: RunFolder.run_config gives a RunConfig (None, where asked, for a
    folder without a record); the keys of older versions stay in its `record`."""
    folder = RunFolder(tmp_path)
    assert folder.run_config(required=False) is None
    with pytest.raises(ValueError, match="config.yaml"):
        folder.run_config()
    folder.config_path.write_text(yaml.safe_dump({"benchmark": "hpatches", "method": "old", "match_options": {"a": 1}}))
    config = folder.run_config(required=False)
    assert isinstance(config, RunConfig) and config.record["match_options"] == {"a": 1}
    # a record without versions is not given this process's (the writer's default)
    assert config.versions == {} and config.identity is None and config.path == folder.config_path


def test_an_unreadable_evaluation_block_is_named(tmp_path):
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump({"benchmark": "hpatches", "method": "x", "evaluation": "fast"}))
    with pytest.raises(ValueError) as error:
        evaluation_of(RunConfig.read(path))
    assert str(error.value).startswith(f"{path}: its evaluation settings cannot be read")
    path.write_text(yaml.safe_dump({"benchmark": "hpatches", "method": "x", "evaluation": {"seed": 4, "newer": 1}}))
    assert evaluation_of(RunConfig.read(path), seed=9).seed == 9  # a key of a newer record is ignored


# --------------------------------------------------------------------------- one reload of a run's pairs


@pytest.fixture(scope="module")
def limited_run(shared_data, tmp_path_factory):
    """A run made with a dataset option, --limit and --skip-bad, from another working directory's
    view of the root (a relative path would not survive; dataset_load holds it absolute)."""
    root = shared_data / "hpatches-sequences-release"
    out = tmp_path_factory.mktemp("cfg") / "sift"
    args = ["hpatches", "--root", root, "--sequences", "v_boat", "--sequences", "i_leuven", "--limit", "7",
            "--skip-bad", "--out", out, "--matcher", "sift"]
    result = invoke(*args)
    assert result.exit_code == 0, result.output
    return out


def _run_pair_names(out: Path) -> list[str]:
    return list(pd.read_csv(RunFolder(out).per_pair_path)["pair"])


@pytest.mark.slow  # its limited run (shared with the next two): 16 s in the fast set under a load of about 7 on the shared 2-core machine (docs/development.md, Testing)
def test_the_reload_gives_the_run_s_pairs(limited_run):
    loaded = load_run_pairs(limited_run)
    names = [p.name for p in loaded.pairs]
    assert names == _run_pair_names(limited_run) and len(names) == 7
    assert {n.split("/")[0] for n in names} <= {"v_boat", "i_leuven"}
    assert loaded.config.limit == 7 and loaded.options["sequences"] and dataset_source(loaded.config)[1] is True
    assert all(p.H is not None for p in loaded.pairs)  # with their ground truth


@pytest.mark.slow  # the limited run above: built only where one of its users runs
def test_without_dataset_load_the_dataset_block_gives_the_same_pairs(limited_run, tmp_path):
    record = RunFolder(limited_run).run_config().record
    record.pop("dataset_load")
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(record))
    assert [p.name for p in load_run_pairs(tmp_path).pairs] == _run_pair_names(limited_run)


@pytest.mark.slow  # the limited run above: built only where one of its users runs
def test_every_reloader_gives_the_same_pairs(limited_run):
    from e3cm_bench.reporting.drawings import _dataset_pairs
    from e3cm_bench.gate.ensemble import _dataset_of
    from e3cm_bench.reporting.runs import load_run

    run = load_run(limited_run)
    expected = _run_pair_names(limited_run)
    notes: list[str] = []
    assert list(_dataset_pairs(run, notes)) == expected and not notes  # the report's drawings
    assert [p.name for p in _dataset_of(run.run_config)] == expected  # the noise ensemble


@pytest.mark.slow  # 13 s in the fast set under a load of about 7 on the shared 2-core machine (docs/development.md, Testing)
def test_a_sampled_run_reloads_its_sample(shared_data, tmp_path):
    root = shared_data / "hpatches-sequences-release"
    out = tmp_path / "sampled"
    result = invoke("hpatches", "--root", root, "--sample", "5", "--sample-seed", "3", "--limit", "4", "--out", out,
                    "--matcher", "sift")
    assert result.exit_code == 0, result.output
    expected = _run_pair_names(out)
    assert [p.name for p in load_run_pairs(out).pairs] == expected
    record = RunFolder(out).run_config().record
    record.pop("dataset_load")  # the dataset block records the sample too
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(record))
    assert [p.name for p in load_run_pairs(tmp_path).pairs] == expected


# --------------------------------------------------------------------------- the one reader


READERS = {"load_yaml", "safe_yaml", "safe_load", "load", "full_load", "unsafe_load", "open", "read_text", "read_bytes"}
CONFIG_NAMES = ("config_path", "CONFIG", "config.yaml")


def config_reads(source: str) -> list[int]:
    """Lines where a module reads a run's config.yaml itself: a YAML load, open or read of an
    expression that names the config file."""
    lines = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Call):
            func = node.func
            name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
            target = ast.unparse(func.value) if isinstance(func, ast.Attribute) else ""
            args = " ".join(ast.unparse(a) for a in node.args) + " " + target
            if name in READERS and any(n in args for n in CONFIG_NAMES):
                lines.append(node.lineno)
    return lines


def test_the_scan_finds_a_raw_reader():
    assert config_reads("cfg = load_yaml(folder.config_path)\n") == [1]
    assert config_reads("import yaml\nx = yaml.safe_load((out / 'config.yaml').read_text())\n") == [2, 2]
    assert config_reads("x = load_yaml(path, what='experiment config')\n") == []


# Every YAML file the package and the scripts read, by the function that reads it: a run's
# config.yaml in storage/run_config.py only; the others are not run records. No script reads YAML.
YAML_READERS = {
    ("e3cm_bench/storage/run_config.py", "RunConfig.read"),  # config.yaml
    ("e3cm_bench/storage/run_config.py", "RunConfig.read_if_present"),  # config.yaml
    ("e3cm_bench/pipeline/experiments.py", "load_experiment"),  # an experiment config (paper/configs/*.yaml)
    ("e3cm_bench/pipeline/experiments.py", "merge_experiment"),  # the experiment config copied into a reproduce's OUT
    ("e3cm_bench/apps/calibration/run.py", "run_calibration"),  # a calibration folder's set file (calibrate.yaml)
    ("e3cm_bench/ground/files.py", "safe_yaml"), ("e3cm_bench/ground/files.py", "load_yaml_text"),  # the loader itself
    ("e3cm_bench/ground/files.py", "load_yaml"),
}
YAML_CALLS = {"load_yaml", "safe_yaml", "safe_load", "full_load", "unsafe_load"}


def yaml_reads(source: str) -> set[str]:
    """The functions (Class.method or function) of a module that call a YAML loader."""
    found = set()

    def visit(node, scope: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                visit(child, f"{scope}.{child.name}" if scope else child.name)
                continue
            if isinstance(child, ast.Call):
                func = child.func
                name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
                module = ast.unparse(func.value) if isinstance(func, ast.Attribute) else ""
                if name in YAML_CALLS or (module == "yaml" and name == "load"):
                    found.add(scope)
            visit(child, scope)

    visit(ast.parse(source), "")
    return found


def test_the_yaml_scan_names_the_reading_function():
    assert yaml_reads("class A:\n    def f(self):\n        return load_yaml(self.path)\n") == {"A.f"}
    assert yaml_reads("def g(p):\n    return yaml.safe_load(p.read_text())\n") == {"g"}


def raw_config_readers(root: Path = REPO) -> dict[str, list]:
    """The modules and scripts below `root` that read config.yaml themselves (config_reads) or
    read YAML in a function YAML_READERS does not list, each with where."""
    readers = {}
    for path in sorted(p for folder in SCANNED for p in (root / folder).rglob("*.py")):
        source, name = path.read_text(), path.relative_to(root).as_posix()
        found = config_reads(source)
        if found:
            readers[name] = found
        others = {(name, scope) for scope in yaml_reads(source)} - YAML_READERS
        if others:
            readers[name] = sorted(others)
    return readers


def test_the_reader_scan_covers_the_scripts(tmp_path):
    """A script reading a run's config.yaml itself is found, by either scan: a YAML load of
    anything (the config under another name) and a read of a path naming the file."""
    script = tmp_path / "scripts" / "results" / "bad.py"
    script.parent.mkdir(parents=True)
    script.write_text("import yaml\n"
                      "def summary(run):\n    return yaml.safe_load((run / 'config.yaml').read_text())\n"
                      "def other(config):\n    return yaml.safe_load(config.read_text())\n")
    (tmp_path / "e3cm_bench").mkdir()
    assert raw_config_readers(tmp_path) == {"scripts/results/bad.py": [("scripts/results/bad.py", "other"),
                                                                       ("scripts/results/bad.py", "summary")]}
    script.write_text("def read(run):\n    return open(run / 'config.yaml').read()\n")
    assert raw_config_readers(tmp_path) == {"scripts/results/bad.py": [2]}


def test_no_module_or_script_but_run_config_reads_config_yaml():
    # the scan reads the package and the scripts, not empty folders
    assert (REPO / "e3cm_bench" / "storage" / "run_config.py").is_file() and (REPO / "scripts" / "results").is_dir(), REPO
    readers = raw_config_readers()
    assert not readers, f"read config.yaml through RunConfig.read (storage/run_config.py): {readers}"
