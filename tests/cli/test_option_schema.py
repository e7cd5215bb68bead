"""The benchmark commands and the run's configuration agree, option for option.

A run's configuration has its sections: the method (options.METHOD_OPTIONS, into a MethodSpec),
the evaluation (eval_options.EVAL_OPTIONS, into EvalSettings), the dataset (the benchmark's
DatasetOptions and the sample), the run (RunRequest's fields), the match stage (MatchOptions')
and how the shards run (Scale's). Every option of a benchmark command is a key of one section,
and every key a user sets is an option of every benchmark command: a command that lists an
option no section declares, or a section's key no command offers, fails here. The toy options of
tests/pipeline/test_toy_options.py show docs/development.md's recipes end to end.
"""

from __future__ import annotations

import dataclasses
import inspect

import pytest
import typer
import yaml
from typer.testing import CliRunner

from e3cm_bench.benchmarks import BENCHMARKS, get_benchmark
from e3cm_bench.benchmarks.base import Benchmark
from e3cm_bench.benchmarks.eval_options import EVAL_OPTIONS
from e3cm_bench.cli.benchmarks import Scale, benchmark_command
from e3cm_bench.method.options import METHOD_OPTIONS
from e3cm_bench.pipeline.experiments import load_experiment
from e3cm_bench.pipeline.request import RunRequest
from e3cm_bench.pipeline.match_options import MatchOptions
from e3cm_bench.storage.run_config import SAMPLE_OPTIONS

from helpers import flat

# Keys of a section that no command offers, each with its reason.
API_ONLY = {
    "benchmark": "the command itself",
    "method": "built from the method options",
    "ev": "built from the evaluation options",
    "options": "built from the match stage's options",
    "dataset": "a PairList object, from Python",
    "dataset_options": "built from the dataset options",
    "dataset_load": "how a given dataset loads again, from Python (reproduce, merge)",
    "given": "what the user gave, kept by the run resolver (pipeline/resolve.py) for the record",
    "spill_mb": "the disk for the feature maps, from Python (the command takes half the free disk)",
}
# Command options that are no key of the run: they change how its files look, not what it holds.
OUTPUT_ONLY = {"plot_format": "the plots' file format"}


def sections(bench: Benchmark) -> dict[str, set[str]]:
    names = lambda cls: {f.name for f in dataclasses.fields(cls)}  # noqa: E731
    return {
        "method": set(METHOD_OPTIONS),
        "evaluation": set(bench.eval_option_names),
        "dataset": {o.name for o in bench.command_options()} | set(SAMPLE_OPTIONS),
        "run": names(RunRequest) - set(API_ONLY),
        "match": names(MatchOptions) - set(API_ONLY),
        "scale": names(Scale),
    }


def parameters(bench: Benchmark) -> dict[str, inspect.Parameter]:
    return dict(inspect.signature(benchmark_command(bench)).parameters)


@pytest.mark.parametrize("name", sorted(BENCHMARKS))
def test_every_option_of_a_benchmark_command_is_a_key_of_the_configuration(name):
    bench = get_benchmark(name)
    declared = set().union(*sections(bench).values()) | set(OUTPUT_ONLY)
    stray = sorted(set(parameters(bench)) - declared)
    assert not stray, f"{name}: options no section of the configuration declares: {stray}"


@pytest.mark.parametrize("name", sorted(BENCHMARKS))
def test_every_key_a_user_sets_is_an_option_of_every_benchmark_command(name):
    bench = get_benchmark(name)
    offered = set(parameters(bench))
    for section, keys in sections(bench).items():
        missing = sorted(keys - offered)
        assert not missing, f"{name}: the {section} section's {missing} are on no option of its command"


@pytest.mark.parametrize("name", sorted(EVAL_OPTIONS))
def test_an_evaluation_option_has_its_declared_flag_and_help(name):
    """On the command of each benchmark that takes it (EvalOption.benchmarks), on no other."""
    option = EVAL_OPTIONS[name]
    for bench in ("hpatches", "sfm"):
        result = CliRunner().invoke(typer_app_of(get_benchmark(bench)), [bench, "--help"], env={"COLUMNS": "200"})
        assert (option.flag in result.output) == option.applies_to(bench), (bench, option.flag)
        assert (flat(option.help.replace("\\[", "["))[:40] in flat(result.output)) == option.applies_to(bench)


def test_each_evaluation_option_names_a_field_of_the_settings_and_resolve_eval_fills_it():
    from dataclasses import fields as dataclass_fields

    from e3cm_bench.benchmarks import EvalSettings

    known = {f.name for f in dataclass_fields(EvalSettings)} | {"ransac_px"}  # ransac_px: Benchmark.ransac_field
    assert {o.field for o in EVAL_OPTIONS.values()} <= known
    ev = get_benchmark("megadepth").resolve_eval(given={"pose_estimator": "poselib", "ransac_px": 2.0,
                                                        "repeats": 2, "interval_seeds": 4})
    assert (ev.estimator, ev.pose_ransac_px, ev.repeats, ev.interval_seeds) == ("poselib", 2.0, 2, 4)


def test_an_unknown_evaluation_name_is_one_line_with_the_nearest_and_sfm_declares_what_it_refuses():
    with pytest.raises(ValueError, match=r"'ransac_pix' is not an evaluation option \(did you mean 'ransac_px'\?\)"):
        get_benchmark("hpatches").resolve_eval(given={"ransac_pix": 2})
    with pytest.raises(ValueError, match="--repeats does not apply to sfm"):
        get_benchmark("sfm").resolve_eval(given={"repeats": 3})
    assert get_benchmark("sfm").resolve_eval(given={"repeats": 1, "interval_seeds": None}).interval_seeds == 1


def typer_app_of(bench: Benchmark) -> typer.Typer:
    """A one-command application holding the benchmark's command, built now (from the tables as
    they are now)."""
    app = typer.Typer()
    app.command(bench.name)(benchmark_command(bench))

    @app.callback()
    def main() -> None:  # a callback keeps the command a subcommand, as in e3cm-bench
        pass

    return app


@pytest.mark.parametrize("content, words", [
    ({"benchmark": "hpatches", "methods": [{"matcher": "sift"}], "evalution": {}},
     "'evalution' is not a key of an experiment (did you mean 'evaluation'?)"),
    ({"benchmark": "hpatches", "methods": [{"matcher": "sift", "ratoi": 0.8}]},
     "methods[0]: 'ratoi' is not a key of a method (did you mean 'ratio'?)"),
    ({"benchmark": "hpatches", "methods": [{"matcher": "sift"}], "evaluation": {"ransac": 2}},
     "evaluation: 'ransac' is not an evaluation option (did you mean 'ransac_px'?)"),
    ({"benchmark": "hpatches", "methods": [{"matcher": "sift"}], "evaluation": {"repeats": "two"}},
     "evaluation: 'repeats' must be a whole number >= 0, got 'two'"),
    ({"benchmark": "hpatches", "methods": [{"matcher": "sift"}], "evaluation": [1]},
     "'evaluation' must be a mapping of evaluation options"),
])
def test_an_experiment_config_refuses_an_unknown_key_naming_the_nearest(tmp_path, content, words):
    config = tmp_path / "bad.yaml"
    config.write_text(yaml.safe_dump(content))
    with pytest.raises(ValueError) as error:
        load_experiment(config)
    message = str(error.value)
    assert message.startswith(str(config)) and words in message and "\n" not in message


def test_an_experiment_configs_evaluation_section_is_the_runs(tmp_path, shared_data):
    """`evaluation:` in an experiment config reaches the run's EvalSettings, as the flags do, and
    its config.yaml records it: the same section name a run's record has."""
    from e3cm_bench.pipeline.experiments import reproduce
    from e3cm_bench.storage.run_config import RunConfig

    config = tmp_path / "toy.yaml"
    config.write_text(yaml.safe_dump({"benchmark": "hpatches", "dataset": {"sequences": ["v_graffiti"]},
                                      "evaluation": {"ransac_px": 2.5, "interval_seeds": 2},
                                      "methods": [{"matcher": "sift", "max_side": 240}]}))
    request = RunRequest("hpatches", tmp_path / "out", root=shared_data / "hpatches-sequences-release", limit=1)
    reproduce(config, request, compare=False)
    record = RunConfig.read(tmp_path / "out" / "sift")
    assert record.record["evaluation"]["homography_ransac_px"] == 2.5
    assert record.record["evaluation"]["interval_seeds"] == 2


def test_the_python_api_names_the_nearest_field_of_a_mistyped_keyword(tmp_path):
    from e3cm_bench import run_benchmark

    with pytest.raises(TypeError, match=r"'limt' is not a field of a run's request \(did you mean 'limit'\?\)"):
        run_benchmark("hpatches", tmp_path / "out", None, eval_only=True, limt=3)


def test_every_option_of_reconstruct_is_a_key_of_the_configuration():
    """`reconstruct` lists its options by name; each one is still a key of a section: the method's,
    the folder set's (FolderOptions: its dataset options), its evaluation's (the mapper, its seeds, the
    merge radius), the run's, the match stage's, the shards'."""
    from e3cm_bench.cli.reconstruct import reconstruct
    from e3cm_bench.sfm.own_images import RECONSTRUCT, FolderOptions

    names = lambda cls: {f.name for f in dataclasses.fields(cls)}  # noqa: E731
    declared = (set(METHOD_OPTIONS) | names(FolderOptions) | names(RunRequest) | names(MatchOptions) | names(Scale)
                | set(RECONSTRUCT.eval_option_names) | {"images"})  # the folder: the request's root
    given = set(inspect.signature(inspect.unwrap(reconstruct)).parameters)
    assert given and not sorted(given - declared)


def test_every_option_of_import_is_a_key_of_the_configuration():
    """`import` scores another tool's matches as a run is scored: every evaluation option from its
    table, the dataset options of every benchmark, the run's; besides them only its sources (one
    --FORMAT per interchange format) and their pixel origin."""
    from e3cm_bench.cli.data import import_matches
    from e3cm_bench.interchange.registry import formats

    bench_options = {o.name for b in BENCHMARKS.values() for o in b.command_options()}
    names = lambda cls: {f.name for f in dataclasses.fields(cls)}  # noqa: E731
    declared = (set(METHOD_OPTIONS) | set(EVAL_OPTIONS) | bench_options | names(RunRequest) | set(OUTPUT_ONLY)
                | set(formats()) | {"pixel_origin"})
    given = set(inspect.signature(import_matches).parameters)
    assert set(EVAL_OPTIONS) <= given
    assert not sorted(given - declared)
