"""A first run that fails must not block its own correction: a folder whose run
wrote no matches takes new settings, one that holds matches still refuses them; a finished
run leaves no lock file behind; an imported run is labelled by its source's name."""

from __future__ import annotations

import fcntl
import os
from pathlib import Path

import numpy as np
import pytest
import yaml
from rich.console import Console

import e3cm_bench.backbones.loading as backbones_module
from e3cm_bench.ground import locks as locks_module
from e3cm_bench.ground.locks import FolderLock
from e3cm_bench.ground.matches import Matches
from e3cm_bench.storage import RunFolder
from helpers import flat, invoke, one_line_error

SMALL = ["--sequences", "v_boat", "--limit", "1", "--max-side", "240"]


def identity(backbone: str) -> dict:
    return {"matcher": "e3cm", "backbone": backbone}


def folder_with_config(path: Path, backbone: str) -> RunFolder:
    folder = RunFolder(path)
    path.mkdir(parents=True)
    folder.write_config({"benchmark": "hpatches", "method": "e3cm", "identity": identity(backbone)})
    return folder


def test_a_folder_without_matches_takes_new_settings_and_says_so(tmp_path):
    folder = folder_with_config(tmp_path / "run", "vgg19")
    (folder.path / "notes.txt").write_text("mine")  # a user's file stays
    console = Console(record=True, width=200)
    assert folder.previous(identity("efficientnet_lite0"), "hpatches", console=console) is None
    said = console.export_text()
    assert f"{folder.path}: holds no matches of its earlier settings (identity); starting anew" in said
    assert not folder.config_path.exists() and (folder.path / "notes.txt").read_text() == "mine"


def test_a_folder_with_matches_still_refuses_other_settings(tmp_path):
    folder = folder_with_config(tmp_path / "run", "vgg19")
    folder.cache().write("v_boat/1-2", Matches(np.zeros((3, 2), np.float32), np.ones((3, 2), np.float32), np.ones(3, np.float32)), {})
    assert folder.holds_matches()
    with pytest.raises(ValueError, match="made with other settings"):
        folder.previous(identity("efficientnet_lite0"), "hpatches", console=Console(record=True))
    assert folder.config_path.exists()  # nothing was removed
    # the same settings resume
    assert folder.previous(identity("vgg19"), "hpatches").identity == identity("vgg19")


def test_the_offline_backbone_after_a_failed_vgg19_run(shared_data, tmp_path, monkeypatch):
    # The first hour: the default backbone's weights cannot be downloaded; the error names the
    # offline backbone, and the same command with it runs in the same folder.
    torch_home = tmp_path / "torch_home"
    torch_home.mkdir()
    monkeypatch.setenv("TORCH_HOME", str(torch_home))
    monkeypatch.setattr(backbones_module, "imagenet_weights_url", lambda spec: "http://127.0.0.1:9/vgg19-dcbb9e9d.pth")
    root, out = shared_data / "hpatches-sequences-release", tmp_path / "hp"
    line = one_line_error(invoke("hpatches", "--root", root, "--out", out, *SMALL))
    assert "vgg19" in line and "--weights" in line and "--backbone efficientnet_lite0" in line
    assert (out / "config.yaml").is_file()  # the failed run had claimed the folder

    result = invoke("hpatches", "--root", root, "--out", out, *SMALL, "--backbone", "efficientnet_lite0")
    assert result.exit_code == 0, (result.output, result.exception)
    assert "holds no matches of its earlier settings (backbone" in flat(result.output)
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["identity"]["backbone"] == "efficientnet_lite0"
    assert (out / "summary.csv").is_file()
    assert not (out / ".lock").exists()  # a finished folder keeps no lock file

    # Now the folder holds matches: other settings are refused as before.
    line = one_line_error(invoke("hpatches", "--root", root, "--out", out, *SMALL, "--matcher", "sift"))
    assert "made with other settings" in line and "--overwrite" in line


def test_the_lock_file_goes_with_the_lock(tmp_path):
    with FolderLock(tmp_path) as lock:
        assert lock.path.is_file() and str(os.getpid()) in lock.path.read_text()
    assert not (tmp_path / ".lock").exists()


def test_a_lock_taken_on_a_removed_file_is_taken_again(tmp_path, monkeypatch):
    # The race the removal opens: B opens .lock, its holder A removes it and releases, B's flock
    # then succeeds on a file no longer in the folder while C locks a new one. B must notice.
    real_flock, calls = fcntl.flock, []

    def flock_after_the_holder_left(fd, operation):
        if not calls:  # B's first try: A removes the file and C creates another in between
            (tmp_path / ".lock").unlink()
            (tmp_path / ".lock").write_text("")
        calls.append(fd)
        return real_flock(fd, operation)

    monkeypatch.setattr(locks_module.fcntl, "flock", flock_after_the_holder_left)
    with FolderLock(tmp_path) as lock:
        assert len(calls) == 2  # the first lock was on the removed file: taken again on the new one
        held, there = os.fstat(lock._fd), os.stat(lock.path)
        assert (held.st_dev, held.st_ino) == (there.st_dev, there.st_ino)


@pytest.mark.parametrize(("fmt", "attribute", "path", "label"), [
    ("npz", "folder", "runs/my_matches", "my_matches"),
    ("hloc", "matches", "outputs/matches-superpoint-lightglue_pairs-sfm.h5", "superpoint-lightglue_pairs-sfm"),
    ("hloc", "matches", "out/aliked-hloc/matches.h5", "aliked-hloc"),
    ("gluefactory", "predictions", "results/hpatches/sp+lg-official/predictions.h5", "sp+lg-official"),
    ("colmap", "database", "work/disk-lightglue/database.db", "disk-lightglue"),
    ("colmap", "database", "work/orb.db", "orb"),
])
def test_an_import_is_labelled_by_its_source_name(tmp_path, fmt, attribute, path, label):
    from types import SimpleNamespace

    from e3cm_bench.pipeline.imported import source_label

    assert source_label(SimpleNamespace(format=fmt, **{attribute: tmp_path / path})) == label


def test_an_imported_run_carries_the_source_name(shared_data, tmp_path):
    # A run exported to npz and imported back is labelled by the npz folder's name, not "imported-npz".
    root = shared_data / "hpatches-sequences-release"
    run = tmp_path / "sift_run"
    assert invoke("hpatches", "--root", root, "--out", run, "--matcher", "sift", *SMALL).exit_code == 0
    assert invoke("export", run, tmp_path / "sift-exported", "--to", "npz").exit_code == 0
    back = tmp_path / "back"
    result = invoke("import", "hpatches", "--root", root, "--out", back, "--npz", tmp_path / "sift-exported", *SMALL[:4],
                    "--interval-seeds", 1, "--ransac-px", 2.5)  # the evaluation options, from their table
    assert result.exit_code == 0, (result.output, result.exception)
    record = yaml.safe_load((back / "config.yaml").read_text())
    assert record["method"] == "sift-exported"
    assert record["evaluation"]["interval_seeds"] == 1 and record["evaluation"]["homography_ransac_px"] == 2.5
    assert not (back / ".lock").exists()


def test_the_runs_below_a_folder_are_not_the_copies_inside_a_report(tmp_path):
    from e3cm_bench.reporting.site import MARKER

    assert RunFolder.REPORT_MARKER == MARKER
    for run in ("table1/sift", "table1/report/runs/01"):
        (tmp_path / run).mkdir(parents=True)
        (tmp_path / run / "config.yaml").write_text("{}")
        (tmp_path / run / "summary.csv").write_text("n_pairs\n1\n")
    (tmp_path / "table1" / "report" / MARKER).write_text("")
    assert [f.path for f in RunFolder.find(tmp_path / "table1")] == [tmp_path / "table1" / "sift"]
    assert [f.path for f in RunFolder.find(tmp_path)] == [tmp_path / "table1" / "sift"]
