"""Robustness round eight (issue 81), items 1, 2, 3, 6, 8 and 9: no folder made or removed
through a link (a `.feature-spill` link inside --out deleted its target's 0/ folder), `check
--update` never writes over a run's own files, `table --out t6/` is a folder, two sweeps into
one --out never share a cell by label, --repeats bounded wherever it is given, and a --pairs
file read in bounded, linear time. Each case failed before its fix (issue 81 says how)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from e3cm_bench.ground.folders import fresh_folder, remove_folder
from e3cm_bench.storage.folder import RunFolder
from helpers import invoke, one_line_error

HPATCHES = "hpatches-sequences-release"


@pytest.fixture(scope="module")
def boat(shared_data, tmp_path_factory) -> Path:
    """An HPatches root with the one sequence v_boat (the shared sample's)."""
    root = tmp_path_factory.mktemp("data") / "hpatches"
    shutil.copytree(shared_data / HPATCHES / "v_boat", root / "v_boat")
    return root


def planted(tmp_path: Path) -> Path:
    """A user's folder holding 0/notes.txt: what a link planted in an output folder points at."""
    victim = tmp_path / "victim"
    (victim / "0").mkdir(parents=True)
    (victim / "0" / "notes.txt").write_text("precious")
    return victim


# ----------------------------------------------------------------------- 1. never through a link


def test_a_spill_link_in_out_is_refused_and_its_target_kept(boat, tmp_path):
    """Before: a deep matcher's run at default settings removed the link's target's 0/ folder
    (the spill store's close) and exited 0."""
    victim = planted(tmp_path)
    out = tmp_path / "run"
    out.mkdir()
    (out / ".feature-spill").symlink_to(victim)
    line = one_line_error(invoke("hpatches", "--root", boat, "--out", out, "--matcher", "direct", "--backbone",
                                 "efficientnet_lite0", "--max-side", 160, "--limit", 1))
    assert str(out / ".feature-spill") in line and "symbolic link" in line
    assert (victim / "0" / "notes.txt").read_text() == "precious"


def test_remove_folder_refuses_a_link_and_a_file_and_removes_links_inside_not_their_targets(tmp_path):
    victim = planted(tmp_path)
    link = tmp_path / "spill"
    link.symlink_to(victim)
    for call in (lambda: remove_folder(link), lambda: remove_folder(link, ignore_errors=True),
                 lambda: fresh_folder(link)):
        with pytest.raises(ValueError, match="is a symbolic link"):
            call()
    assert (victim / "0" / "notes.txt").read_text() == "precious"
    ours = fresh_folder(tmp_path / "ours" / "0")
    (ours / "inside").symlink_to(victim)  # a link inside a folder of ours: removed, its target kept
    remove_folder(tmp_path / "ours")
    assert not (tmp_path / "ours").exists() and (victim / "0" / "notes.txt").read_text() == "precious"
    (tmp_path / "file").write_text("mine")
    with pytest.raises(ValueError, match=r"file: is not a folder \(the drawings go there\)"):
        fresh_folder(tmp_path / "file", "the drawings go there")
    remove_folder(tmp_path / "absent")  # nothing there: nothing done


def test_the_spill_store_makes_and_removes_its_folder_never_through_a_link(tmp_path):
    torch = pytest.importorskip("torch")
    from e3cm_bench.matchers.spill import SpillStore

    victim = planted(tmp_path)
    (tmp_path / "spill").symlink_to(victim / "0")
    store = SpillStore(tmp_path / "spill", max_mb=1)
    with pytest.raises(ValueError, match="is a symbolic link"):
        store.write("a", [torch.zeros(4)])
    with pytest.raises(ValueError, match="is a symbolic link"):
        store.close()
    (tmp_path / "root").symlink_to(victim)  # the stage's spill folder a link: its 0/ is the victim's
    store = SpillStore(tmp_path / "root" / "0", max_mb=1)
    with pytest.raises(ValueError, match="root: is a symbolic link"):
        store.write("a", [torch.zeros(4)])
    with pytest.raises(ValueError, match="root: is a symbolic link"):
        store.close()
    assert sorted(p.name for p in (victim / "0").iterdir()) == ["notes.txt"]
    store = SpillStore(tmp_path / "own", max_mb=1)
    assert store.write("a", [torch.ones(4)]) and store.read("a", "cpu")[0].sum() == 4
    store.close()
    assert not (tmp_path / "own").exists()


def test_drawings_shards_and_data_folders_are_never_made_through_a_link(tmp_path):
    from e3cm_bench.data.archives import place
    from e3cm_bench.pipeline.shards import shard_dir

    victim = planted(tmp_path)
    out = tmp_path / "run"
    out.mkdir()
    (out / "viz").symlink_to(victim / "0")
    with pytest.raises(ValueError, match="viz: is a symbolic link"):
        RunFolder(out).drawing_path("v_boat/1_2")
    (out / "shards").symlink_to(victim)
    with pytest.raises(ValueError, match="shards: is a symbolic link"):
        shard_dir(out, (1, 2))
    unpacked = fresh_folder(tmp_path / ".data.extracting")
    (unpacked / "top").mkdir()
    (tmp_path / "data").symlink_to(victim)
    with pytest.raises(ValueError, match="data: is a symbolic link"):
        place(unpacked, tmp_path / "data", tmp_path / "data.zip")
    with pytest.raises(ValueError, match="viz: is a symbolic link"):
        RunFolder(out).clear()  # --overwrite: refused before anything is removed
    assert (out / "viz").is_symlink() and (victim / "0" / "notes.txt").read_text() == "precious"


# ----------------------------------------------------------------- 2. check --update over a run


@pytest.fixture(scope="module")
def sift_run(shared_data, tmp_path_factory) -> Path:
    """A SIFT run of two pairs of the shared HPatches sample."""
    from helpers import sift_hpatches_run

    return sift_hpatches_run(shared_data, tmp_path_factory.mktemp("runs") / "sift")


@pytest.mark.parametrize("name", ["matches.h5", "summary.csv", "cost.csv", "per_pair.csv", "config.yaml"])
def test_check_update_never_writes_a_baseline_over_a_runs_own_file(sift_run, name):
    """Before: `check --update --baseline RUN/summary.csv` replaced the run's summary, exit 0."""
    before = {p.name: p.read_bytes() for p in sift_run.iterdir() if p.is_file()}
    line = one_line_error(invoke("check", sift_run, "--update", "--baseline", sift_run / name))
    assert f"{sift_run / name}: a file of the run folder {sift_run}" in line and "--baseline" in line
    assert {p.name: p.read_bytes() for p in sift_run.iterdir() if p.is_file()} == before


def test_check_summary_never_appends_to_a_runs_own_file(sift_run, tmp_path):
    baseline = tmp_path / "baseline.csv"
    assert invoke("check", sift_run, "--update", "--baseline", baseline).exit_code == 0
    before = (sift_run / "summary.csv").read_bytes()
    line = one_line_error(invoke("check", sift_run, "--baseline", baseline, "--summary", sift_run / "summary.csv"))
    assert "--summary" in line and (sift_run / "summary.csv").read_bytes() == before


# ------------------------------------------------------------------ 3. a trailing slash: a folder


def test_table_out_with_a_trailing_slash_is_a_folder(sift_run, tmp_path):
    """Before: `table --out t6/` wrote t6.csv and t6.md beside the folder (the / dropped)."""
    (tmp_path / "t6.csv").write_text("mine\n")
    result = invoke("table", sift_run, "--out", f"{tmp_path / 't6'}/", "--no-paper")
    assert result.exit_code == 0, result.output
    assert (tmp_path / "t6" / "table.csv").is_file() and (tmp_path / "t6" / "table.md").is_file()
    assert (tmp_path / "t6.csv").read_text() == "mine\n" and not (tmp_path / "t6.md").exists()


# ------------------------------------------------------------------------- 8. --repeats bounded


def test_repeats_is_bounded_on_the_command_line_in_a_record_and_in_a_config(sift_run, tmp_path):
    """Before: --repeats 1000000000 matched, then evaluated without end (killed at 40 s; here a
    60 s timeout ran out). Now refused in one line before a pair is matched, wherever given."""
    import yaml

    from e3cm_bench.benchmarks.eval_settings import MAX_REPEATS
    from e3cm_bench.benchmarks.eval_options import EVAL_OPTIONS

    assert f"at most {MAX_REPEATS}" in EVAL_OPTIONS["repeats"].help
    root = Path(yaml.safe_load((sift_run / "config.yaml").read_text())["dataset"]["root"])
    line = one_line_error(invoke("hpatches", "--root", root, "--out", tmp_path / "flag", "--matcher", "sift",
                                 "--limit", 1, "--repeats", 10**9))
    assert line == f"error: --repeats must be 1 to {MAX_REPEATS}, got 1000000000"
    assert not (tmp_path / "flag" / "matches.h5").exists()
    record = yaml.safe_load((sift_run / "config.yaml").read_text())
    record["evaluation"]["repeats"] = 10**9
    edited = tmp_path / "edited.yaml"
    edited.write_text(yaml.safe_dump(record))
    line = one_line_error(invoke("rerun", edited, "--out", tmp_path / "record"))
    assert f"must be 1 to {MAX_REPEATS}" in line and not (tmp_path / "record" / "matches.h5").exists()
    config = tmp_path / "experiment.yaml"
    config.write_text(yaml.safe_dump({"benchmark": "hpatches", "methods": [{"matcher": "sift"}],
                                      "evaluation": {"repeats": 10**9}}))
    line = one_line_error(invoke("reproduce", config, "--out", tmp_path / "config", "--root", root, "--limit", 1))
    assert f"must be 1 to {MAX_REPEATS}" in line and not list((tmp_path / "config").rglob("matches.h5"))
    from e3cm_bench.benchmarks import EvalSettings

    assert EvalSettings(repeats=MAX_REPEATS).repeats == MAX_REPEATS  # the bound itself is taken


# ------------------------------------------------------------ 9. a --pairs file read in bounds


KITTI = "megadepth_test_1500/Undistorted_SfM/kitti00/images"


def test_a_pairs_file_with_a_4_mb_line_is_one_line(shared_data, tmp_path):
    """Before: `reconstruct --pairs` with one line of 4 MB parsed it in quadratic time (shlex:
    not done after 60 s). Now the line's length is refused in one line naming the file and line."""
    from e3cm_bench.datasets.base import MAX_LINE_CHARS

    images = shared_data / KITTI
    listed = tmp_path / "pairs.txt"
    listed.write_text("000100.png 000101.png\n" + "a" * (4 << 20) + " 000102.png\n")
    line = one_line_error(invoke("reconstruct", images, "--out", tmp_path / "r", "--matcher", "sift",
                                 "--pairs", listed))
    assert line == (f"error: {listed}: line 2 holds {(4 << 20) + 11} characters, over the {MAX_LINE_CHARS} a line "
                    "of a list may hold")
    assert not (tmp_path / "r" / "matches.h5").exists()


def test_a_list_over_its_size_bound_is_refused_before_it_is_read(tmp_path, monkeypatch):
    from e3cm_bench.datasets import base
    from e3cm_bench.datasets.base import DatasetError, text_lines

    listed = tmp_path / "pairs.txt"
    listed.write_text("a b\n" * 1000)
    monkeypatch.setattr(base, "MAX_LIST_BYTES", 1000)
    with pytest.raises(DatasetError, match=rf"^{listed}: 4000 bytes, over the 1000 a list may hold$"):
        list(text_lines(listed))


@pytest.mark.parametrize("line", [
    "a b", "  a\tb  ", "'a b.png' c", "a\\ b.png c", "'it'\"'\"'s.png' x", '"a \\" b" c', '"a\\x" b', "a''b c",
    "'' x", "a'b c'd e", "\"a'b\" c", "a\\\\b c", "x#y z", "é ü.png",
])
def test_the_linear_name_split_reads_what_shlex_reads(line):
    """name_pairs' split (linear in the line) reads each line as shlex.split does, the quoting
    pair_line writes (shlex.quote) included."""
    import shlex

    from e3cm_bench.datasets.base import split_names

    assert split_names(line) == shlex.split(line)


def test_the_linear_name_split_refuses_what_shlex_refuses():
    import shlex

    from e3cm_bench.datasets.base import split_names

    for line in ("'a b", '"a b', "a \\"):
        with pytest.raises(ValueError) as theirs:
            shlex.split(line)
        with pytest.raises(ValueError, match=str(theirs.value)):
            split_names(line)


def test_names_written_by_pair_line_are_read_back():
    import random

    from e3cm_bench.datasets.base import pair_line, split_names

    rng = random.Random(81)
    alphabet = "ab c'\"\\$#\t*?é/"
    for _ in range(2000):
        names = ["".join(rng.choice(alphabet) for _ in range(rng.randint(1, 12))) for _ in range(2)]
        assert split_names(pair_line(*names)) == names


def test_a_yfcc_pair_list_with_a_long_line_is_one_line(shared_data, tmp_path):
    from e3cm_bench.datasets.base import MAX_LINE_CHARS, DatasetError
    from e3cm_bench.datasets.yfcc import YFCC100M

    listed = tmp_path / "pairs.txt"
    first = (shared_data / "yfcc_test_pairs_with_gt.txt").read_text().splitlines()[0]
    listed.write_text(first + "\n" + "x" * (MAX_LINE_CHARS + 1) + "\n")
    with pytest.raises(DatasetError, match=rf"{listed}: line 2 holds {MAX_LINE_CHARS + 1} characters"):
        YFCC100M(tmp_path, pairs=listed)


# --------------------------------------------------------- 6. two sweeps into one --out


@pytest.fixture(scope="module")
def kitti_runs(shared_data, tmp_path_factory) -> dict[str, Path]:
    """Three SIFT runs of four KITTI pairs: `sift`, `weak` (300 keypoints), and `other`: 100
    keypoints but labelled `sift` too, as a run of another day may be."""
    where = tmp_path_factory.mktemp("kitti")
    root = shared_data / "megadepth_test_1500"
    runs = {}
    for name, extra in (("sift", []), ("weak", ["--label", "weak", "--set", "max_keypoints=300"]),
                        ("other", ["--label", "sift", "--set", "max_keypoints=100"])):
        runs[name] = where / name
        result = invoke("megadepth", "--root", root, "--scene-info", root / "scene_info" / "kitti00_seq.npz",
                        "--matcher", "sift", "--limit", 4, "--max-side", 320, "--out", runs[name], *extra)
        assert result.exit_code == 0, result.output
    return runs


def swept(out: Path, *runs: Path):
    import pandas as pd

    result = invoke("sweep", *runs, "--out", out, "--estimators", "opencv-ransac", "--thresholds", "0.5px",
                    "--seeds", 1)
    assert result.exit_code == 0, result.output
    return pd.read_csv(out / "sweep.csv").set_index("run")["auc@20"]


def test_a_second_sweep_into_one_out_never_takes_another_runs_cells_by_label(kitti_runs, tmp_path):
    """Before: the second sweep found cells/CELL.csv with a column `sift_s0` over the same pairs
    and took the first sweep's `sift` errors for the other run labelled sift (exit 0)."""
    import pandas as pd

    own = [pd.read_csv(kitti_runs[n] / "per_pair.csv")["err_pose"].to_numpy() for n in ("sift", "other")]
    assert not np.allclose(own[0], own[1], equal_nan=True)  # two runs that a shared label would mix up
    first = swept(tmp_path / "sweep", kitti_runs["sift"], kitti_runs["weak"])
    second = swept(tmp_path / "sweep", kitti_runs["other"], kitti_runs["weak"])
    alone = swept(tmp_path / "alone", kitti_runs["other"], kitti_runs["weak"])
    assert second["sift"] == pytest.approx(alone["sift"]) and second["weak"] == pytest.approx(first["weak"])
    cell = pd.read_csv(tmp_path / "sweep" / "cells" / "opencv-ransac_0.5px.csv")
    assert len(cell.columns) == 1 + 3  # pair, and one column per run ever swept here (keyed, not labelled)
    assert swept(tmp_path / "sweep", kitti_runs["sift"], kitti_runs["weak"]).equals(first)  # resumed, same


def test_a_sweep_folder_in_use_is_refused_in_one_line(kitti_runs, tmp_path):
    out = tmp_path / "sweep"
    with RunFolder(out).lock():  # another sweep writing it
        line = one_line_error(invoke("sweep", kitti_runs["sift"], kitti_runs["weak"], "--out", out,
                                     "--estimators", "opencv-ransac", "--thresholds", "0.5px", "--seeds", 1))
    assert f"{out}: another run is using this folder" in line and not (out / "sweep.csv").exists()


def test_a_link_at_the_sweeps_cells_folder_is_refused_and_its_target_kept(kitti_runs, tmp_path):
    """Item 1 for the sweep: OUT/cells as a link to a user's folder is refused in one line, and
    nothing is written into the folder it points at."""
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "keep.txt").write_text("mine")
    out = tmp_path / "sweep"
    out.mkdir()
    (out / "cells").symlink_to(victim, target_is_directory=True)
    line = one_line_error(invoke("sweep", kitti_runs["sift"], kitti_runs["weak"], "--out", out,
                                 "--estimators", "opencv-ransac", "--thresholds", "0.5px", "--seeds", 1))
    assert "cells" in line and "link" in line
    assert sorted(p.name for p in victim.iterdir()) == ["keep.txt"]
