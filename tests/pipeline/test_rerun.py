"""`e3cm-bench rerun RUN --out NEW` (issue 71): a run made again from its config.yaml alone gives
the same per_pair.csv byte for byte, for a two-view benchmark, a method of a YAML experiment
config run by `reproduce`, an sfm run on the shared KITTI frames and a `reconstruct` run."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import yaml

from helpers import invoke, kitti_frames, one_line_error


def rerun_gives_the_same_rows(run: Path, out: Path, given: Path | None = None) -> None:
    result = invoke("rerun", given or run, "--out", out)
    assert result.exit_code == 0, result.output
    assert (out / "per_pair.csv").read_bytes() == (run / "per_pair.csv").read_bytes()
    before, after = (yaml.safe_load((f / "config.yaml").read_text()) for f in (run, out))
    for block in ("benchmark", "identity", "evaluation"):
        assert after[block] == before[block], block


def test_an_hpatches_run_reruns_from_its_folder_and_from_its_config(shared_data, tmp_path):
    root = shared_data / "hpatches-sequences-release"
    run = tmp_path / "run"
    made = invoke("hpatches", "--root", root, "--matcher", "sift", "--limit", 3, "--seed", 4, "--out", run)
    assert made.exit_code == 0, made.output
    rerun_gives_the_same_rows(run, tmp_path / "again")
    rerun_gives_the_same_rows(run, tmp_path / "from-yaml", given=run / "config.yaml")
    assert yaml.safe_load((tmp_path / "again" / "config.yaml").read_text())["evaluation"]["seed"] == 4


def test_a_yaml_configured_reproduce_method_reruns(shared_data, tmp_path):
    config = tmp_path / "exp.yaml"
    config.write_text(yaml.safe_dump({"benchmark": "hpatches", "max_side": 320, "methods": [
        {"label": "sift-tight", "matcher": "sift", "settings": {"ratio": 0.7}}]}))
    root = shared_data / "hpatches-sequences-release"
    made = invoke("reproduce", config, "--root", root, "--out", tmp_path / "exp", "--limit", 3, "--no-compare")
    assert made.exit_code == 0, made.output
    run = next(p.parent for p in (tmp_path / "exp").rglob("per_pair.csv"))
    # the method's own `given`: its entry in the config's names (the experiment's max_side among them),
    # which the rerun resolves to this very run (not falling back on the identity block)
    from e3cm_bench.pipeline.rerun import rerun_request

    given = yaml.safe_load((run / "config.yaml").read_text())["given"]["method"]
    assert (given["matcher"], given["settings"], given["max_side"], given["label"]) == ("sift", {"ratio": 0.7}, 320,
                                                                                         "sift-tight")
    assert rerun_request(run, tmp_path / "probe").given is not None
    rerun_gives_the_same_rows(run, tmp_path / "again")


@pytest.fixture(scope="module")
def kitti6(shared_data, tmp_path_factory) -> Path:
    return kitti_frames(shared_data, 6, tmp_path_factory.mktemp("kitti6") / "kitti6.npz")


def test_an_sfm_run_on_the_kitti_frames_reruns(shared_data, kitti6, tmp_path):
    run = tmp_path / "run"
    made = invoke("sfm", "--root", shared_data / "megadepth_test_1500", "--scene-info", kitti6, "--window", 2,
                  "--matcher", "sift", "--mapper-seeds", 2, "--out", run)
    assert made.exit_code == 0, made.output
    rerun_gives_the_same_rows(run, tmp_path / "again")
    evaluation = yaml.safe_load((tmp_path / "again" / "config.yaml").read_text())["evaluation"]
    assert evaluation["mapper_seeds"] == 2  # the evaluation came from the record


def test_a_reconstruct_run_reruns(tmp_path):
    from e3cm_bench.apps.synth.multiview import write_multiview

    write_multiview(tmp_path / "room", n_views=4)
    run = tmp_path / "run"
    made = invoke("reconstruct", tmp_path / "room" / "images", "--out", run, "--matcher", "sift", "--window", 2)
    assert made.exit_code == 0, made.output
    rerun_gives_the_same_rows(run, tmp_path / "again")


def test_what_cannot_be_rerun_is_one_line(shared_data, tmp_path):
    root = shared_data / "hpatches-sequences-release"
    run = tmp_path / "run"
    assert invoke("hpatches", "--root", root, "--matcher", "sift", "--limit", 1, "--out", run).exit_code == 0
    line = one_line_error(invoke("rerun", run, "--out", run))
    assert "is the run itself" in line
    line = one_line_error(invoke("rerun", tmp_path / "nothing", "--out", tmp_path / "new"))
    assert "nothing" in line
    shutil.copy(run / "config.yaml", tmp_path / "broken.yaml")
    record = yaml.safe_load((tmp_path / "broken.yaml").read_text())
    record["identity"] = {"matcher": "my-plugin", "plugin": {"package": "x"}}
    (tmp_path / "broken.yaml").write_text(yaml.safe_dump(record))
    line = one_line_error(invoke("rerun", tmp_path / "broken.yaml", "--out", tmp_path / "new"))
    assert "broken.yaml" in line and "built-in matcher" in line


def test_an_edited_record_is_a_new_run_and_a_misspelt_key_is_refused(shared_data, tmp_path):
    """config.yaml edited into another run: the edited evaluation is taken; a key no record holds
    (a misspelt edit, which the tolerant readers would skip) is refused naming the nearest one."""
    root = shared_data / "hpatches-sequences-release"
    run = tmp_path / "run"
    assert invoke("hpatches", "--root", root, "--matcher", "sift", "--limit", 2, "--out", run).exit_code == 0
    record = yaml.safe_load((run / "config.yaml").read_text())
    record["given"]["evaluation"] = {"ransac_px": 1.0}  # the flag's name, as it was typed
    edited = tmp_path / "edited.yaml"
    edited.write_text(yaml.safe_dump(record))
    assert invoke("rerun", edited, "--out", tmp_path / "one-px").exit_code == 0
    assert yaml.safe_load((tmp_path / "one-px" / "config.yaml").read_text())["evaluation"]["homography_ransac_px"] == 1.0
    # a resolved block edited, its given as written: the block's edit holds, as in a record without given
    record = yaml.safe_load((run / "config.yaml").read_text())
    record["evaluation"]["homography_ransac_px"] = 1.5
    edited.write_text(yaml.safe_dump(record))
    assert invoke("rerun", edited, "--out", tmp_path / "block").exit_code == 0
    assert yaml.safe_load((tmp_path / "block" / "config.yaml").read_text())["evaluation"]["homography_ransac_px"] == 1.5
    record = yaml.safe_load((run / "config.yaml").read_text())
    record["given"]["evaluation"] = {"ransac_pix": 1.0}
    edited.write_text(yaml.safe_dump(record))
    line = one_line_error(invoke("rerun", edited, "--out", tmp_path / "misspelt"))
    assert "given: evaluation: 'ransac_pix' is not an evaluation option of hpatches (did you mean 'ransac_px'?)" in line
    for part, key, nearest in (("evaluation", "homography_ransac_pix", "homography_ransac_px"),
                               ("identity", "matchr", "matcher"), (None, "evalution", "evaluation")):
        bad = yaml.safe_load((run / "config.yaml").read_text())
        (bad[part] if part else bad)[key] = 1
        path = tmp_path / f"bad-{key}.yaml"
        path.write_text(yaml.safe_dump(bad))
        line = one_line_error(invoke("rerun", path, "--out", tmp_path / f"new-{key}"))
        assert str(path) in line and (f"{part}.{key}" if part else key) in line and f"did you mean '{nearest}'" in line
        assert not (tmp_path / f"new-{key}").exists()
