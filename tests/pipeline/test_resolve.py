"""The one resolver (pipeline/resolve.py): a run's request from what its user gave, by section, in the
tables' own names; the same names from the flag to the record, and back through rerun."""

from __future__ import annotations

import re

import pytest
import yaml

from helpers import invoke, one_line_error

from e3cm_bench.pipeline.resolve import resolve_request


@pytest.mark.parametrize("given, words", [
    ({"evaluaton": {}}, "'evaluaton' is not a section of a run's options (did you mean 'evaluation'?)"),
    ({"method": {"matchr": "sift"}}, "method: 'matchr' is not a method option of hpatches (did you mean 'matcher'?)"),
    ({"dataset": {"ransac_px": 2}},
     "dataset: 'ransac_px' is not a dataset option of hpatches; it is an option of the evaluation section"),
    ({"run": {"max_side": 320}}, "run: 'max_side' is not a run option of hpatches; it is an option of the method section"),
    ({"evaluation": {"mapper_seeds": 3}}, "evaluation: 'mapper_seeds' is not an evaluation option of hpatches"),
    ({"dataset": {"scene_info": "x.npz"}}, "dataset: 'scene_info' is not a dataset option of hpatches"),
    ({"evaluation": {"ransac_px": -1}}, "--ransac-px must be a finite number, above 0"),
    ({"method": {"matcher": "sifft"}}, "sifft"),
    ({"dataset": "v_boat"}, "dataset: must map option names to values, got str"),
])
def test_a_name_or_value_no_table_holds_is_one_line_before_anything_loads(given, words, tmp_path):
    full = {"run": {"out": tmp_path / "out", "root": tmp_path}}
    for section, values in given.items():
        full[section] = {**full.get(section, {}), **values} if isinstance(values, dict) else values
    with pytest.raises(ValueError, match=re.escape(words)):
        resolve_request("hpatches", full)
    assert not (tmp_path / "out").exists()


def test_sfms_mapper_seeds_is_an_evaluation_option_and_refused_as_a_dataset_one(tmp_path):
    """sfm's reconstruction protocol is typed evaluation options: `evaluation: {mapper_seeds: 3}` (an
    int, as YAML gives it) is the run's evaluation, `dataset: {mapper_seeds: 3}` is refused naming its
    section, and a word outside the option's choices is one line naming the flag."""
    run = {"out": tmp_path / "out", "root": tmp_path}
    request = resolve_request("sfm", {"run": run, "evaluation": {"mapper_seeds": 2, "mapper": "incremental"}})
    assert (request.ev.mapper_seeds, request.ev.mapper, request.ev.merge) == (2, "incremental", "auto")
    assert request.ev.record()["mapper_seeds"] == 2 and request.given["evaluation"]["mapper_seeds"] == 2
    with pytest.raises(ValueError, match=re.escape("dataset: 'mapper_seeds' is not a dataset option of sfm; it is "
                                                   "an option of the evaluation section")):
        resolve_request("sfm", {"run": run, "dataset": {"mapper_seeds": 3}})
    with pytest.raises(ValueError, match=re.escape("--mapper must be one of global, incremental, got 'glomap'")):
        resolve_request("sfm", {"run": run, "evaluation": {"mapper": "glomap"}})
    with pytest.raises(ValueError, match=re.escape("--mapper-seeds must be a whole number")):
        resolve_request("sfm", {"run": run, "evaluation": {"mapper_seeds": 101}})
    assert "mapper" not in resolve_request("hpatches", {"run": run}).ev.record()


def test_the_python_api_and_the_command_resolve_to_one_request(shared_data, tmp_path):
    """The same options given by section (the Python API) and as flags: the same method, evaluation
    and dataset; the command's record keeps what was typed, in the flags' names."""
    from dataclasses import asdict

    from e3cm_bench.pipeline.runner import run_benchmark

    root = shared_data / "hpatches-sequences-release"
    flags = invoke("hpatches", "--root", root, "--out", tmp_path / "cli", "--matcher", "sift", "--max-side", 320,
                   "--limit", 2, "--ransac-px", 2, "--sequences", "v_boat")
    assert flags.exit_code == 0, flags.output
    given = {"method": {"matcher": "sift", "max_side": 320}, "evaluation": {"ransac_px": 2.0},
             "dataset": {"sequences": ["v_boat"]}, "run": {"out": tmp_path / "api", "root": root, "limit": 2}}
    request = resolve_request("hpatches", given)
    run_benchmark(request)
    cli, api = (yaml.safe_load((tmp_path / d / "config.yaml").read_text()) for d in ("cli", "api"))
    for block in ("identity", "evaluation", "dataset_load"):
        assert cli[block] == api[block], block
    assert cli["given"] == {"method": {"matcher": "sift", "max_side": 320}, "evaluation": {"ransac_px": 2.0},
                            "dataset": {"sequences": ["v_boat"]},
                            "run": {"out": str(tmp_path / "cli"), "root": str(root), "limit": 2}}
    assert asdict(request.ev)["homography_ransac_px"] == 2.0
    assert (tmp_path / "cli" / "per_pair.csv").read_bytes() == (tmp_path / "api" / "per_pair.csv").read_bytes()


def test_an_edited_given_reruns_in_the_names_typed(shared_data, tmp_path):
    """rerun resolves the record's given: --max-side edited there (the flag's name) is the new run."""
    root = shared_data / "hpatches-sequences-release"
    run = tmp_path / "run"
    assert invoke("hpatches", "--root", root, "--out", run, "--matcher", "sift", "--limit", 1,
                  "--max-side", 320).exit_code == 0
    record = yaml.safe_load((run / "config.yaml").read_text())
    record["given"]["method"]["max_side"] = 240
    (tmp_path / "edited.yaml").write_text(yaml.safe_dump(record))
    assert invoke("rerun", tmp_path / "edited.yaml", "--out", tmp_path / "again").exit_code == 0
    again = yaml.safe_load((tmp_path / "again" / "config.yaml").read_text())
    assert again["identity"]["max_side"] == 240 and again["given"]["method"]["max_side"] == 240
    record["given"]["run"] = {"limit": "all"}  # a run's where and how much are the rerun's own: not read
    record["given"]["methd"] = {}
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(record))
    line = one_line_error(invoke("rerun", tmp_path / "bad.yaml", "--out", tmp_path / "bad"))
    assert "bad.yaml: given: 'methd' is not a section of a run's options (did you mean 'method'" in line
