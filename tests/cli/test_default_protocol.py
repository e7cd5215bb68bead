"""One default protocol: an experiment config without `protocol:` gets, under `reproduce`, the
method and evaluation settings its benchmark's command gets without --protocol (WxBS and EVD:
the reference's estimator, wxbs; `reproduce` once took e3cm-bench's own there). Nothing is
matched: the run functions are replaced by ones that keep what they were handed."""

from __future__ import annotations

from dataclasses import replace

import pytest
import yaml

from e3cm_bench.benchmarks import Benchmark, get_benchmark
from helpers import invoke


@pytest.fixture
def handed(monkeypatch):
    """What the benchmark command and `reproduce` hand to the run, which does not happen."""
    calls: dict = {}
    monkeypatch.setattr("e3cm_bench.pipeline.runner.run_benchmark",
                        lambda request, **kw: calls.setdefault("command", vars(request)))
    monkeypatch.setattr("e3cm_bench.pipeline.experiments.run_methods",
                        lambda benchmark, jobs, dataset, **kw: calls.setdefault("reproduce", {**kw, "jobs": jobs}))
    monkeypatch.setattr("e3cm_bench.pipeline.experiments._table_and_report", lambda *a, **kw: None)
    # no data needed: the pairs are never matched
    monkeypatch.setattr(Benchmark, "load_dataset", lambda self, root, skip_bad=False, **options: [])
    return calls


@pytest.mark.parametrize("name", ["wxbs", "evd"])
def test_a_config_without_protocol_gets_the_commands_protocol(tmp_path, handed, name):
    config = tmp_path / "mine.yaml"  # a user's own config: no `protocol:` key
    config.write_text(yaml.safe_dump({"benchmark": name, "methods": [{"matcher": "sift", "max_side": 320}]}))
    assert invoke(name, "--root", tmp_path, "--out", tmp_path / "cmd", "--matcher", "sift",
                  "--max-side", 320).exit_code == 0
    assert invoke("reproduce", config, "--root", tmp_path, "--out", tmp_path / "rep").exit_code == 0
    command, reproduced = handed["command"], handed["reproduce"]
    (_, method, _), = reproduced["jobs"]  # (folder, method, given)
    # the reference's estimator (MAGSAC++) on both paths, the very same settings
    assert command["ev"].protocol == reproduced["ev"].protocol == get_benchmark(name).default_protocol == "wxbs"
    assert reproduced["ev"] == command["ev"]
    assert replace(method, label="") == replace(command["method"], label="")
