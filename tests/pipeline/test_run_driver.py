"""Every kind of run goes through the one run pipeline (pipeline/driver.py: run_pipeline, whose
steps open_run and finish_run are spied on here), and every refusal to mix matches is RunFolder's."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from e3cm_bench.benchmarks import get_benchmark
from e3cm_bench.storage.cache import MatchCache
from e3cm_bench.apps.calibration.run import CalibrationSettings, run_calibration
from e3cm_bench.pipeline.imported import import_run
from e3cm_bench.interchange import NpzSource
from e3cm_bench.method.spec import MethodSpec
from e3cm_bench.gate.ensemble import build_ensemble
from e3cm_bench.reporting.runs import load_run
from e3cm_bench.storage import RunFolder
from e3cm_bench.pipeline import driver
from e3cm_bench.pipeline.request import RunRequest
from e3cm_bench.pipeline.runner import run_benchmark
from e3cm_bench.ground.files import CSV_FLOAT_FORMAT
from helpers import accuracy_summary, invoke

SEQUENCES = {"sequences": ["v_boat"]}


@pytest.fixture
def spy(monkeypatch):
    """The folders each step of the driver was called on, in order."""
    seen = SimpleNamespace(opened=[], finished=[])
    open_run, finish_run = driver.open_run, driver.finish_run

    def opening(folder, overwrite=False):
        seen.opened.append(Path(folder.path))
        return open_run(folder, overwrite)

    def finishing(run, *args, **kwargs):
        seen.finished.append(Path(run.folder.path))
        return finish_run(run, *args, **kwargs)

    monkeypatch.setattr(driver, "open_run", opening)
    monkeypatch.setattr(driver, "finish_run", finishing)
    return seen


@pytest.fixture
def hpatches(shared_data) -> Path:
    return shared_data / "hpatches-sequences-release"


def sift_run(root: Path, out: Path, **kwargs):
    return run_benchmark("hpatches", out, MethodSpec.create("sift"), root=root, dataset_options=SEQUENCES, limit=2,
                         **kwargs)


def npz_folder(run: Path, folder: Path) -> Path:
    cache = MatchCache(run / "matches.h5")
    for name in cache.names():
        m = cache.read(name)
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        np.savez(folder / f"{name}.npz", keypoints0=m.keypoints0, keypoints1=m.keypoints1, scores=m.scores)
    return folder


def test_a_benchmark_run_and_an_import_go_through_the_driver(hpatches, spy, tmp_path):
    sift_run(hpatches, tmp_path / "run")
    assert spy.opened == spy.finished == [tmp_path / "run"]
    benchmark = get_benchmark("hpatches")
    dataset = benchmark.load_dataset(hpatches, **SEQUENCES)
    import_run(RunRequest(benchmark, tmp_path / "imported", root=hpatches, dataset=dataset, limit=2),
               NpzSource(npz_folder(tmp_path / "run", tmp_path / "npz")))
    assert spy.opened == spy.finished == [tmp_path / "run", tmp_path / "imported"]
    # the same numbers; the run's cost columns (time, memory) are its own: imported matches have none
    assert (tmp_path / "imported" / "summary.csv").read_bytes() == accuracy_summary(tmp_path / "run" / "summary.csv").to_csv(
        index=False, float_format=CSV_FLOAT_FORMAT).encode()


@pytest.mark.slow  # 13 s in the fast set under a load of about 7 on the shared 2-core machine (docs/development.md, Testing)
def test_shards_and_their_merge_go_through_the_driver(hpatches, spy, tmp_path):
    out = tmp_path / "sharded"
    sift_run(hpatches, out, shard=(1, 2))
    sift_run(hpatches, out, shard=(2, 2))  # the last shard to finish merges (shards.merge_run)
    shards = [RunFolder(out).shard((k, 2)).path for k in (1, 2)]
    assert spy.opened == spy.finished == [*shards, out]
    merged = yaml.safe_load((out / "config.yaml").read_text())
    assert merged["dataset"]["n_pairs_evaluated"] == 2 and merged["shards"]["count"] == 2


@pytest.mark.slow  # 24 s in the fast set under a load of about 7 on the shared 2-core machine (docs/development.md, Testing)
def test_a_calibration_opens_each_method_folder_through_the_driver(spy, tmp_path):
    root = tmp_path / "seq"
    assert invoke("synth", "stereo", "--out", root, "--frames", 3, "--seed", 2).exit_code == 0
    run_calibration(root, tmp_path / "cal", [MethodSpec.create("sift")], CalibrationSettings(frames=(1,)))
    assert spy.opened == spy.finished == [tmp_path / "cal" / "sift"]


@pytest.mark.slow  # 34 s in the fast set under a load of about 7 on the shared 2-core machine (docs/development.md, Testing)
def test_the_noise_ensemble_reruns_through_the_driver(hpatches, spy, tmp_path):
    sift_run(hpatches, tmp_path / "run")
    table = build_ensemble([load_run(tmp_path / "run")], [0, 1], tmp_path / "work")
    rerun = [tmp_path / "work" / "hpatches" / f"draw-{d:03d}" / "run" for d in (0, 1)]
    assert spy.opened[1:] == spy.finished[1:] == rerun
    assert sorted(set(table["draw"])) == [0, 1]


def raised_in_run_folder(excinfo) -> bool:
    return Path(excinfo.traceback[-1].path).name == "folder.py"


@pytest.mark.slow  # 20 s in the fast set under a load of about 7 on the shared 2-core machine (docs/development.md, Testing)
def test_every_refusal_to_mix_matches_is_run_folders(hpatches, tmp_path):
    out = tmp_path / "run"
    sift_run(hpatches, out)
    with pytest.raises(ValueError, match="made with other settings") as excinfo:  # another method
        run_benchmark("hpatches", out, MethodSpec.create("sift", max_side=320), root=hpatches, dataset_options=SEQUENCES,
                      limit=2)
    assert raised_in_run_folder(excinfo)

    benchmark = get_benchmark("hpatches")
    dataset = benchmark.load_dataset(hpatches, **SEQUENCES)
    npz = npz_folder(out, tmp_path / "npz")
    imported = RunRequest(benchmark, tmp_path / "imported", root=hpatches, dataset=dataset, limit=2)
    import_run(imported, NpzSource(npz))
    first = sorted(npz.rglob("*.npz"))[0]
    with np.load(first) as m:
        np.savez(first, keypoints0=m["keypoints0"][:-1], keypoints1=m["keypoints1"][:-1], scores=m["scores"][:-1])
    with pytest.raises(ValueError, match="imported pair file") as excinfo:  # other sources
        import_run(imported, NpzSource(npz))
    assert raised_in_run_folder(excinfo)

    sharded = tmp_path / "sharded"
    sift_run(hpatches, sharded, shard=(1, 2))
    with pytest.raises(ValueError, match="differs from shard 1-of-2") as excinfo:  # shards of two commands
        # the last shard to finish merges, and the merge refuses
        run_benchmark("hpatches", sharded, MethodSpec.create("sift", max_side=320), root=hpatches,
                      dataset_options=SEQUENCES, limit=2, shard=(2, 2))
    assert raised_in_run_folder(excinfo)
