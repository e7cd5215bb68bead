"""A method's options, declared once (e3cm_bench/method/options.py): the command line, the experiment
configs and MethodSpec's validation are made from the one table; full resolution is one value
(0) however it is spelled; the committed experiment configs resolve to the same identities as
before; the launch options refuse what they cannot do in one line."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from e3cm_bench.method import options as opts
from e3cm_bench.benchmarks import BENCHMARKS, get_benchmark
from e3cm_bench.method.protocols import PROTOCOLS, ReferenceProtocol
from e3cm_bench.cli import app
from e3cm_bench.pipeline.experiments import (
    experiment_keys,
    experiment_method,
    experiment_types,
    load_experiment,
    method_types,
)
from e3cm_bench.method.spec import MethodSpec

from helpers import flat, one_line_error

REPO = Path(__file__).resolve().parents[2]
CONFIG_FOLDERS = (REPO / "configs", REPO / "e3cm_bench" / "paper" / "configs")

# Each committed config's methods (label and identity, without weight hashes) under four
# overrides, hashed; computed from the code before the options were declared as data (main at
# 8a34c58) by the same procedure as _config_rows.
CONFIG_IDENTITIES = {
    "design_points_hpatches.yaml": "8be65be7bc822921", "design_points_kitti.yaml": "8be65be7bc822921",
    "e3cm_plus_ablation_hpatches.yaml": "3e394e8fbee01612", "e3cm_plus_ablation_kitti.yaml": "3aa0f3ae03e8773e",
    "e3cm_plus_tuning_hpatches.yaml": "9528e6b3cf470ea0", "e3cm_plus_tuning_kitti.yaml": "73fc4753dd506b98",
    "evd_all.yaml": "b947ee86fc5b96b9", "fig5_backbones.yaml": "b4c3b75099a37d67",
    "refine_ablation_hpatches.yaml": "11e57b0f4b31b661", "refine_ablation_kitti.yaml": "c4e0a2cc720c1320",
    # table1-3 gained the field's rows (issue 68); their other rows still digest to the values before
    # (8bc3734739858c48, e03a4a7c1d6df5c7, e03a4a7c1d6df5c7), checked when these were updated
    "table1_hpatches.yaml": "111ecbe4c04fa7b0", "table2_megadepth.yaml": "64ea651592d3f720",
    "table3_yfcc.yaml": "64ea651592d3f720", "wxbs_all.yaml": "b947ee86fc5b96b9",
}
# Each benchmark's methods (e3cm, sift, dfm) under every protocol it takes and --max-side none,
# 0 and 640, as Benchmark.resolve_method gave them before; same procedure as _command_rows.
COMMAND_IDENTITIES = {
    "evd": "d158682406085334", "hpatches": "5254678c048a2b9c", "megadepth": "fecdb3d19e022b2b",
    "sfm": "0203d98356478bd1", "wxbs": "51e729d651ed1c9f", "yfcc": "207dd3918587c8d3",
}


def _digest(rows) -> str:
    return hashlib.sha256(json.dumps(rows, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _config_rows(path: Path) -> list:
    experiment = load_experiment(path)
    bench = get_benchmark(experiment["benchmark"])
    rows = []
    for backbone, max_side in ((None, None), ("efficientnet_lite0", None), (None, 0), (None, 320)):
        for entry in experiment["methods"]:
            spec = experiment_method(entry, experiment, bench, backbone, max_side, available=False)
            rows.append([spec.label, spec.identity()])
    return rows


def _command_rows(name: str) -> dict:
    bench = BENCHMARKS[name]
    rows = {}
    for protocol, preset in PROTOCOLS.items():
        if preset.benchmarks and name not in preset.benchmarks:
            continue
        for max_side in (None, 0, 640):
            for matcher in ("e3cm", "sift", "dfm"):
                spec = bench.resolve_method(matcher, protocol=protocol, max_side=max_side, available=False)
                rows[f"{name} {protocol} {max_side} {matcher}"] = [spec.label, spec.identity()]
    return rows


def _committed_configs() -> list[Path]:
    return sorted(p for folder in CONFIG_FOLDERS for p in folder.glob("*.yaml"))


def test_every_committed_config_is_known():
    assert {p.name for p in _committed_configs()} == set(CONFIG_IDENTITIES)


@pytest.mark.parametrize("path", _committed_configs(), ids=lambda p: p.name)
def test_a_committed_config_resolves_to_the_identities_it_had(path):
    assert _digest(_config_rows(path)) == CONFIG_IDENTITIES[path.name]


@pytest.mark.parametrize("name", sorted(COMMAND_IDENTITIES))
def test_a_benchmarks_methods_resolve_to_the_identities_they_had(name):
    assert _digest(_command_rows(name)) == COMMAND_IDENTITIES[name]


def test_the_digest_sees_a_change():
    # the identity digests above would pass vacuously if a change did not move them
    rows = _config_rows(REPO / "e3cm_bench" / "paper" / "configs" / "table1_hpatches.yaml")
    rows[0][1]["max_side"] = 640
    assert _digest(rows) != CONFIG_IDENTITIES["table1_hpatches.yaml"]


# ---- declared once: the command line, the configs and the validation are made from the table
def _help(*args: str) -> str:
    result = CliRunner().invoke(app, [*args, "--help"], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    return flat(result.output)


@pytest.mark.parametrize("name", sorted(opts.METHOD_OPTIONS))
def test_a_declared_option_is_in_the_benchmark_commands_help(name):
    option = opts.METHOD_OPTIONS[name]
    text = _help("hpatches")
    for flag in option.flags:
        assert flag in text
    assert flat(option.help.split("{")[0])[:30] in text  # the words before a list the command line fills in


def test_the_experiment_keys_are_those_the_table_places_in_configs():
    in_methods = {n for n, o in opts.METHOD_OPTIONS.items() if o.config in ("method", "both")}
    in_experiment = {n for n, o in opts.METHOD_OPTIONS.items() if o.config in ("experiment", "both")}
    assert set(method_types()) == in_methods and {k: opts.METHOD_OPTIONS[k].kind for k in in_methods} == method_types()
    assert in_experiment <= experiment_keys() and in_experiment <= set(experiment_types())
    assert experiment_keys() - in_experiment == {"name", "benchmark", "dataset", "evaluation", "methods"}
    # the command-line-only options are not config keys (they are matcher settings there)
    assert "precision" not in set(method_types()) | experiment_keys()


@pytest.mark.parametrize("keyword, value, words", [
    ("max_side", -3, "--max-side must be a whole number, from 0 to 1,000,000, got -3"),
    ("max_side", "big", "--max-side must be a whole number, from 0 to 1,000,000, got 'big'"),
    ("backbone", 5, "--backbone must be non-empty text, got 5"),
    ("ratio", "x", "--ratio must be a number or a list of numbers"),
    ("weights", 7, "--weights must be non-empty text, got 7"),
    ("options", [1], "--set must be a mapping"),
])
def test_methodspec_validates_each_option_by_its_declaration(keyword, value, words):
    with pytest.raises(ValueError, match="^" + words.replace("(", r"\(").replace("[", r"\[")):
        MethodSpec.create("sift", **{keyword: value})


def test_an_experiment_value_is_checked_by_the_same_declaration(tmp_path):
    config = tmp_path / "exp.yaml"
    config.write_text(yaml.safe_dump({"benchmark": "hpatches", "methods": [{"matcher": "sift", "ratio": "x"}]}))
    with pytest.raises(ValueError, match=r"methods\[0\]: 'ratio' must be a number or a list of numbers"):
        load_experiment(config)


def test_the_defaults_come_from_the_table():
    values = opts.with_defaults({"matcher": "sift", "max_side": None})
    assert values["backbone"] == "vgg19" and values["seed"] == 0 and values["max_side"] is None
    with pytest.raises(ValueError, match="unknown method option"):
        opts.with_defaults({"maxside": 3})


# ---- full resolution: 0 however it is written
def test_full_resolution_spelled_each_way_gives_one_identity():
    hpatches, megadepth = get_benchmark("hpatches"), get_benchmark("megadepth")
    api = {MethodSpec.create("e3cm", max_side=v).identity()["max_side"] for v in (None, 0)}
    assert api == {None}
    full = megadepth.resolve_method("e3cm", max_side=opts.FULL_RESOLUTION)
    assert full.max_side is None and full == megadepth.resolve_method("e3cm", max_side=0)
    assert megadepth.resolve_method("e3cm").max_side == 1200  # not given: the benchmark's side
    # a protocol table: 0, or None, its older spelling
    assert PROTOCOLS["e3cm-release"].max_side["megadepth"] == opts.FULL_RESOLUTION
    assert megadepth.resolve_method("e3cm", protocol="e3cm-release").max_side is None
    assert hpatches.resolve_method("sift").max_side is None  # HPatches' default side: full
    old = ReferenceProtocol("old", "", (), max_side={"megadepth": None})
    assert old.max_side.get("megadepth", 1200) is None and opts.resolved_side(None) is None


def test_full_resolution_in_an_experiment_config(tmp_path):
    hpatches = get_benchmark("megadepth")
    at_top = {"benchmark": "megadepth", "max_side": 0, "methods": [{"matcher": "sift"}]}
    per_method = {"benchmark": "megadepth", "methods": [{"matcher": "sift", "max_side": 0}]}
    specs = [experiment_method(e["methods"][0], e, hpatches, available=False) for e in (at_top, per_method)]
    assert specs[0] == specs[1] and specs[0].max_side is None
    default = {"benchmark": "megadepth", "max_side": None, "methods": [{"matcher": "sift"}]}
    assert experiment_method(default["methods"][0], default, hpatches, available=False).max_side == 1200


@pytest.mark.parametrize("value", [-1, 2.5, True])
def test_a_side_that_is_neither_full_nor_positive_is_one_line(value):
    with pytest.raises(ValueError, match="max_side must be 0 .full resolution. or a positive whole number"):
        opts.resolved_side(value)


# ---- the command line: one path, and the launch options
@pytest.fixture
def captured(monkeypatch):
    """What the benchmark command hands to the run (run_benchmark, or run_shards), not run."""
    calls = []
    monkeypatch.setattr("e3cm_bench.pipeline.runner.run_benchmark",
                        lambda request, console=None: calls.append(("run", vars(request))))
    monkeypatch.setattr("e3cm_bench.pipeline.launch.run_shards",
                        lambda request, n, devices=None, launcher="local", console=None: calls.append(
                            ("shards", {"n": n, "devices": devices, "launcher": launcher, **vars(request)})))
    return calls


def _run(tmp_path, *args):
    return CliRunner().invoke(app, ["hpatches", "--root", str(tmp_path), "--out", str(tmp_path / "out"),
                                    "--matcher", "sift", *map(str, args)])


def test_the_command_builds_its_method_through_the_one_path(tmp_path, captured):
    assert _run(tmp_path, "--max-side", 0).exit_code == 0
    assert _run(tmp_path, "--max-side", 320, "--ratio", "0.8").exit_code == 0
    full, small = (kw["method"] for _, kw in captured)
    assert full == get_benchmark("hpatches").resolve_method("sift", max_side=0)
    assert small == get_benchmark("hpatches").resolve_method("sift", max_side=320, ratio=(0.8,))
    assert full.max_side is None and small.max_side == 320


def test_an_unknown_launcher_is_one_line(tmp_path, captured):
    line = one_line_error(_run(tmp_path, "--launcher", "sge"))
    assert "--launcher 'sge': choose one of local, slurm" in line and not captured
    line = one_line_error(CliRunner().invoke(app, ["reproduce", "table1", "--out", str(tmp_path / "r"),
                                                   "--root", str(tmp_path), "--launcher", "pbs"]))
    assert "--launcher 'pbs'" in line


@pytest.mark.parametrize("scale", [["--workers", 1], ["--devices", "cpu"], ["--launcher", "slurm", "--shards", 2]])
def test_eval_only_with_shards_that_run_elsewhere_is_refused(tmp_path, captured, scale):
    line = one_line_error(_run(tmp_path, "--eval-only", *scale))
    assert line.startswith("error: --eval-only recomputes the metrics in this process: drop --") and not captured


def test_eval_only_with_one_shard_here_goes_through(tmp_path, captured):
    assert _run(tmp_path, "--eval-only", "--shard", "1/2").exit_code == 0
    assert captured[0][1]["eval_only"] is True and captured[0][1]["shard"] == (1, 2)


def test_device_reaches_the_workers_and_the_array(tmp_path, captured):
    assert _run(tmp_path, "--workers", 1, "--device", "cuda:1").exit_code == 0
    assert _run(tmp_path, "--launcher", "slurm", "--shards", 2, "--device", "cuda").exit_code == 0
    (_, workers), (_, array) = captured
    assert workers["devices"] == ["cuda:1"] and workers["n"] == 1
    assert array["devices"] == ["cuda"] and array["launcher"] == "slurm" and array["n"] == 2


def test_device_and_devices_together_are_refused(tmp_path, captured):
    line = one_line_error(_run(tmp_path, "--devices", "cuda:0,cuda:1", "--device", "cuda:0"))
    assert "--device and --devices do not go together" in line and not captured
