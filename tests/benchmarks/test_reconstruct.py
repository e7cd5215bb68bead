"""`e3cm-bench reconstruct`: a folder of images, no ground truth -> pairs -> the match stage ->
COLMAP's verification and pycolmap's mapper -> a model COLMAP and pycolmap open."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from e3cm_bench.storage.cache import MatchCache
from e3cm_bench.datasets.base import DatasetError
from e3cm_bench.sfm.own_images import ImageFolder, image_names
from helpers import accuracy_summary, invoke, one_line_error

pycolmap = pytest.importorskip("pycolmap")

KITTI = "megadepth_test_1500/Undistorted_SfM/kitti00/images"


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> Path:
    """Five views of the synthetic room (synth/multiview.py), their images only: no ground truth."""
    from e3cm_bench.apps.synth.multiview import write_multiview

    root = tmp_path_factory.mktemp("room")
    write_multiview(root, n_views=5)
    return root / "images"


@pytest.fixture(scope="module")
def room_run(room, tmp_path_factory) -> tuple[Path, object]:
    out = tmp_path_factory.mktemp("room_run") / "run"
    result = invoke("reconstruct", room, "--out", out, "--matcher", "sift")
    return out, result


def test_the_room_is_reconstructed_without_ground_truth(room_run):
    out, result = room_run
    assert result.exit_code == 0
    assert "5 of 5 images registered in 1 model(s)" in " ".join(result.output.split())
    summary = pd.read_csv(out / "summary.csv").iloc[0]
    assert summary["n_pairs"] == 10 and summary["registered_images"] == 5 and summary["largest_model_images"] == 5
    assert summary["points"] > 100 and 1 < summary["mean_track_length"] and summary["mean_reprojection_error"] < 2
    # one model: its own points are the sum's; the message names them beside the folder
    assert summary["largest_model_points"] == summary["points"]
    assert f"holds 5 images and {int(summary['points'])} points" in " ".join(result.output.split())
    per_pair = pd.read_csv(out / "per_pair.csv")
    assert list(per_pair.columns[:3]) == ["pair", "n_matches", "n_duplicates"] and (per_pair["n_verified"] > 0).all()
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["benchmark"] == "reconstruct" and config["dataset"]["pair_graph"] == "exhaustive"
    assert config["dataset"]["reconstruction"]["camera_model"] == "SIMPLE_RADIAL"
    assert (out / "pairs.txt").read_text().splitlines()[0] == "view00.png view01.png"


def test_the_model_opens_in_pycolmap_as_binary_and_as_text(room_run, tmp_path):
    out, _ = room_run
    model = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert sorted(image.name for image in model.images.values()) == [f"view{i:02d}.png" for i in range(5)]
    assert model.num_reg_images() == 5 and len(model.cameras) == 1  # one size, one shared camera
    camera = next(iter(model.cameras.values()))
    assert camera.model_name == "SIMPLE_RADIAL" and camera.params[0] != 1.2 * 640  # refined from COLMAP's guess
    text = tmp_path / "text"
    text.mkdir()
    for path in (out / "sparse" / "0").glob("*.txt"):
        shutil.copy(path, text)
    again = pycolmap.Reconstruction()
    again.read_text(str(text))
    assert again.num_reg_images() == 5 and again.num_points3D() == model.num_points3D()


def test_a_rerun_resumes_and_gives_the_same_model(room, room_run):
    out, _ = room_run
    before = accuracy_summary(out / "summary.csv")
    result = invoke("reconstruct", room, "--out", out, "--matcher", "sift")
    assert result.exit_code == 0 and "evaluating only" in result.output
    # seeded, one thread; the cost columns (the mapping's seconds among them) are measurements
    pd.testing.assert_frame_equal(accuracy_summary(out / "summary.csv"), before)


def test_pair_graphs_and_bad_input(room, tmp_path):
    assert image_names(room) == [f"view{i:02d}.png" for i in range(5)]
    assert [p.name for p in ImageFolder(room, window=1)] == [f"view{i:02d}.png--view{i + 1:02d}.png" for i in range(4)]
    listed = tmp_path / "pairs.txt"
    listed.write_text("# two pairs\nview00.png view02.png\nview03.png view04.png\n")
    # two components that share no image: refused as sfm refuses them (issue 70), unless allowed
    with pytest.raises(DatasetError, match="2 components that share no image.*--allow-disconnected"):
        ImageFolder(room, pairs=listed)
    assert len(ImageFolder(room, pairs=listed, allow_disconnected=True)) == 2
    line = one_line_error(invoke("reconstruct", room, "--out", tmp_path / "r0", "--matcher", "sift", "--pairs", listed))
    assert "components that share no image" in line and not (tmp_path / "r0" / "matches.h5").exists()
    listed.write_text("view00.png nowhere.png\n")
    with pytest.raises(DatasetError, match="line 1 names nowhere.png"):
        ImageFolder(room, pairs=listed)
    line = one_line_error(invoke("reconstruct", room, "--out", tmp_path / "r", "--matcher", "sift", "--pairs", listed))
    assert str(listed) in line and "nowhere.png" in line
    empty = tmp_path / "empty"
    empty.mkdir()
    line = one_line_error(invoke("reconstruct", empty, "--out", tmp_path / "r2", "--matcher", "sift"))
    assert "holds 0 image(s)" in line
    line = one_line_error(invoke("reconstruct", room, "--out", tmp_path / "r3", "--matcher", "sift",
                                 "--camera-model", "OPENCV"))
    assert "--camera-model must be one of SIMPLE_RADIAL, PINHOLE" in line


@pytest.mark.slow  # 37 pairs of SIFT twice and two mappers: about three minutes on 2 cores
def test_kitti_frames_without_ground_truth(shared_data, tmp_path):
    images = shared_data / KITTI
    if not images.is_dir():
        pytest.skip(f"{images} not found")
    out = tmp_path / "kitti"
    result = invoke("reconstruct", images, "--out", out, "--matcher", "sift", "--window", 2)
    assert result.exit_code == 0
    summary = pd.read_csv(out / "summary.csv").iloc[0]
    assert summary["n_images"] == 20 and summary["largest_model_images"] >= 15
    model = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    names = {image.name for image in model.images.values() if image.has_pose}
    assert len(names) >= 15 and names <= set(image_names(images))
    # sfm with the ground truth on the same frames and graph makes the very same matches (what
    # docs/sfm.md says scores them): its pairs are named by the scene_info, ours by the files
    truth = tmp_path / "sfm"
    assert invoke("sfm", "--root", shared_data / "megadepth_test_1500", "--scene-info",
                  shared_data / "megadepth_test_1500/scene_info/kitti00_seq.npz", "--window", 2, "--matcher", "sift",
                  "--out", truth).exit_code == 0
    ours, theirs = MatchCache(out / "matches.h5"), MatchCache(truth / "matches.h5")
    for pair in pd.read_csv(out / "per_pair.csv")["pair"]:
        stems = pair.replace(".png", "")
        a, b = ours.read(pair), theirs.read(f"kitti00_seq/{stems}")
        assert np.array_equal(a.keypoints0, b.keypoints0) and np.array_equal(a.keypoints1, b.keypoints1), pair


def test_cameras_are_colmaps_guess_shared_by_size_and_exif(room, tmp_path):
    """One camera per size and EXIF focal (COLMAP's single_camera: reconstruct's default), each as COLMAP's reader makes it."""
    from PIL import Image

    from e3cm_bench.sfm.uncalibrated import cameras_for

    folder = tmp_path / "mixed"
    folder.mkdir()
    for i in range(3):
        shutil.copy(room / f"view{i:02d}.png", folder / f"a{i}.png")
    with Image.open(room / "view03.png") as image:
        image.resize((320, 240)).save(folder / "small.png")
        exif = Image.Exif()
        exif[0x8769] = {0xA405: 50}  # FocalLengthIn35mmFilm, in the Exif sub-IFD
        image.convert("RGB").save(folder / "exif.jpg", exif=exif)
    names = image_names(folder)
    cameras = cameras_for(folder, names, "SIMPLE_RADIAL", camera_per_image=False)
    assert len({id(c) for c in cameras.values()}) == 3  # the three 640 x 480 PNGs share one
    assert cameras["a0.png"] is cameras["a2.png"] and cameras["small.png"].width == 320
    assert cameras["a0.png"].params[0] == pytest.approx(1.2 * 640) and not cameras["a0.png"].has_prior_focal_length
    assert cameras["exif.jpg"].has_prior_focal_length and cameras["exif.jpg"].params[0] != pytest.approx(1.2 * 640)
    apart = cameras_for(folder, names, "PINHOLE", camera_per_image=True)
    assert len({id(c) for c in apart.values()}) == 5 and apart["a0.png"].model_name == "PINHOLE"


@pytest.fixture(scope="module")
def six_frames(shared_data, tmp_path_factory) -> Path:
    """Six KITTI frames (links to the shared files, no ground truth with them)."""
    source = shared_data / KITTI
    if not source.is_dir():
        pytest.skip(f"{source} not found")
    folder = tmp_path_factory.mktemp("six") / "images"
    folder.mkdir()
    for path in sorted(source.glob("*.png"))[:6]:
        (folder / path.name).symlink_to(path)
    return folder


def _model_numbers(out: Path) -> dict:
    row = pd.read_csv(out / "summary.csv").iloc[0]
    return {key: row[key] for key in ("n_pairs", "registered_images", "n_models", "points", "mean_track_length")}


@pytest.mark.slow  # three runs of 9 SIFT pairs, two of them sharded (worker start-up): about 40 s on 2 cores
def test_shards_and_workers_make_the_unsharded_model(six_frames, tmp_path):
    base = ("reconstruct", six_frames, "--matcher", "sift", "--window", 2)
    assert invoke(*base, "--out", tmp_path / "one").exit_code == 0
    whole = _model_numbers(tmp_path / "one")
    assert whole["registered_images"] == 6 and whole["n_pairs"] == 9 and whole["points"] > 500
    workers = invoke(*base, "--out", tmp_path / "workers", "--workers", 2)
    assert workers.exit_code == 0 and "6 of 6 images registered" in " ".join(workers.output.split())
    assert _model_numbers(tmp_path / "workers") == whole
    first = invoke(*base, "--out", tmp_path / "shards", "--shard", "1/2")
    # a shard alone makes no model in OUT: the last shard's merge does
    assert first.exit_code == 0 and "when the last shard finishes" in " ".join(first.output.split())
    assert not (tmp_path / "shards" / "summary.csv").exists()
    assert invoke(*base, "--out", tmp_path / "shards", "--shard", "2/2").exit_code == 0
    assert _model_numbers(tmp_path / "shards") == whole
    config = yaml.safe_load((tmp_path / "shards" / "config.yaml").read_text())
    assert config["benchmark"] == "reconstruct" and config["shards"]["count"] == 2
    assert pycolmap.Reconstruction(str(tmp_path / "shards" / "sparse" / "0")).num_points3D() == whole["points"]
    # merge from the command line finds reconstruct's benchmark too (it is in no registry)
    merged = invoke("merge", tmp_path / "shards")
    assert merged.exit_code == 0 and _model_numbers(tmp_path / "shards") == whole


def test_shards_of_two_image_folders_are_refused(six_frames, tmp_path):
    other = tmp_path / "other"
    shutil.copytree(six_frames, other, symlinks=True)  # the same names, another folder
    shard = lambda images, *more: invoke("reconstruct", images, "--matcher", "sift", "--window", 1,  # noqa: E731
                                         "--out", tmp_path / "run", "--shard", *more)
    assert shard(six_frames, "1/2").exit_code == 0
    line = one_line_error(shard(other, "2/2"))  # the last shard merges, and the merge refuses
    assert "2-of-2" in line and "dataset_load differs from shard 1-of-2's" in line and "dataset_load.root" in line
    assert not (tmp_path / "run" / "summary.csv").exists()
    line = one_line_error(shard(six_frames, "1/2", "--workers", 2))
    assert "--shard and --workers do not go together" in line
    assert "--shard 3/2: K must be between 1 and N" in one_line_error(shard(six_frames, "3/2"))


def test_pairs_are_bounded_before_any_is_built(tmp_path):
    """3000 tiny images gave 4,498,500 pairs (4.3 GB after 46 s); now a one-line refusal at once."""
    import time

    import cv2

    folder = tmp_path / "many"
    folder.mkdir()
    tiny = np.zeros((4, 4), np.uint8)
    for i in range(3000):
        cv2.imwrite(str(folder / f"{i:04d}.png"), tiny)
    started = time.monotonic()
    line = one_line_error(invoke("reconstruct", folder, "--out", tmp_path / "r", "--matcher", "sift"))
    assert time.monotonic() - started < 60
    assert "3000 images give 4,498,500 pairs (every pair), over the 20,000 a run builds" in line
    assert not (tmp_path / "r" / "matches.h5").exists()
    assert len(ImageFolder(folder, window=2)) == 2 * 3000 - 3  # a window fits under the bound
    with pytest.raises(DatasetError, match="over the 100 a run builds"):
        ImageFolder(folder, window=2, max_pairs=100)


@pytest.mark.parametrize("window", ["0", "1000000000"])
def test_window_is_bounded(room, tmp_path, window):
    line = one_line_error(invoke("reconstruct", room, "--out", tmp_path / "r", "--matcher", "sift", "--window", window))
    assert "--window" in line


def test_no_model_names_only_files_that_exist(tmp_path):
    """Two unrelated noise images: no model; the message named OUT/sparse/0, which did not exist."""
    import cv2

    folder = tmp_path / "noise"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for name in ("a.png", "b.png"):
        cv2.imwrite(str(folder / name), rng.integers(0, 255, (120, 160), dtype=np.uint8))
    out = tmp_path / "r"
    result = invoke("reconstruct", folder, "--out", out, "--matcher", "sift")
    assert result.exit_code == 0, result.output
    said = " ".join(result.output.split())
    assert "no model: 0 of 2 images registered" in said and "sparse/0" not in said
    assert (out / "database.db").is_file()


@pytest.fixture(scope="module")
def kitti_xfeat(shared_data, tmp_path_factory) -> tuple[Path, object]:
    """xfeat on the 20 shared KITTI frames, each with the next 2 (issue 80: 9 registered, the largest
    model 3 images, before reconstruct took sfm's verification and calibrated its focal lengths)."""
    pytest.importorskip("torch")
    images = shared_data / KITTI
    if not images.is_dir():
        pytest.skip(f"{images} not found")
    out = tmp_path_factory.mktemp("kitti_xfeat") / "run"
    return out, invoke("reconstruct", images, "--out", out, "--matcher", "xfeat", "--window", 2)


@pytest.mark.slow  # 37 xfeat pairs and the global mapper: about two minutes on 2 cores
def test_xfeat_registers_the_kitti_frames_in_one_model(kitti_xfeat):
    out, result = kitti_xfeat
    assert result.exit_code == 0, result.output
    summary = pd.read_csv(out / "summary.csv").iloc[0]
    assert summary["registered_images"] >= 18 and summary["largest_model_images"] >= 18
    assert summary["mapper"] == "global" and summary["focals_calibrated"] == 1
    # the cost holds the mapping: seconds per image are the matching's and the mapping's together
    matched = pd.read_csv(out / "cost.csv")["match_seconds"].sum()
    assert summary["mapping_seconds"] > 0
    assert summary["seconds_per_image"] == pytest.approx((matched + summary["mapping_seconds"]) / 20, rel=1e-3)
    # COLMAP's log went to the run's log file, not the terminal
    assert "Duplicate correspondence" not in result.output and "global_pipeline" not in result.output
    assert "global_pipeline" in (out / "mapper.log").read_text()
    model = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    focal = next(iter(model.cameras.values())).params[0]
    assert 600 < focal < 800  # KITTI's is 718; COLMAP's guess, 1.2 x 1241 = 1489, is calibrated away


def test_reconstruct_runs_in_table_report_and_compare(room, room_run, tmp_path):
    """compare says in one line why two reconstructions have no pair score to compare (it refused
    them as having no metric); report builds their page (it stopped on an IndexError: no metric to
    plot the cost against); table lists both with the whole run's cost."""
    first, _ = room_run
    other = tmp_path / "incremental"
    shutil.copytree(first, other)  # the same matches, mapped again by the other mapper
    assert invoke("reconstruct", room, "--out", other, "--matcher", "sift", "--mapper", "incremental",
                  "--label", "sift-incremental").exit_code == 0
    line = one_line_error(invoke("compare", first, other))
    assert "no ground truth, so no pair has a score to compare" in line and "table" in line
    report = invoke("report", first, other, "--out", tmp_path / "report")
    assert report.exit_code == 0, report.output
    assert (tmp_path / "report" / "index.html").is_file() and "no ground truth" in report.output
    assert list((tmp_path / "report" / "img").glob("*.jpg"))  # drawings, without correctness colours
    table = invoke("table", first, other, "--out", tmp_path / "table")
    assert table.exit_code == 0, table.output
    rows = pd.read_csv(tmp_path / "table.csv")
    assert len(rows) == 2 and (rows["registered_images"] == 5).all() and (rows["seconds_per_image"] > 0).all()


def test_verification_and_mapper_are_sfms_and_recorded(room, tmp_path):
    """reconstruct verifies with sfm's preset (one table: sfm/mapper.py VERIFY_OPTIONS) and takes
    sfm's --mapper and --mapper-seeds; config.yaml records them, and each seed's model is kept."""
    from e3cm_bench.sfm.mapper import VERIFY_OPTIONS

    out = tmp_path / "run"
    result = invoke("reconstruct", room, "--out", out, "--matcher", "sift", "--window", 2, "--mapper", "incremental",
                    "--mapper-seeds", 2)
    assert result.exit_code == 0, result.output
    config = yaml.safe_load((out / "config.yaml").read_text())
    recorded = config["dataset"]["reconstruction"]
    assert recorded["verification"]["options"] == VERIFY_OPTIONS and VERIFY_OPTIONS["max_H_inlier_ratio"] == 1.0
    assert config["evaluation"]["mapper"] == "incremental" and config["evaluation"]["mapper_seeds"] == 2
    assert config["evaluation"]["verification"] == "colmap" and config["given"]["evaluation"]["mapper_seeds"] == 2
    assert "mapper" not in config["dataset_load"]["options"]
    per_seed = pd.read_csv(out / "per_seed.csv")
    assert list(per_seed["seed"]) == [0, 1] and (per_seed["registered_images"] == 5).all()
    assert (out / "seed-1" / "sparse" / "0").is_dir() and (out / "mapper.log").is_file()
    summary = pd.read_csv(out / "summary.csv").iloc[0]
    assert summary["mapper"] == "incremental" and summary["mapper_seeds"] == 2
    line = one_line_error(invoke("reconstruct", room, "--out", tmp_path / "r", "--matcher", "sift",
                                 "--mapper", "glomap"))
    assert "--mapper must be one of global, incremental" in line


def test_a_fragmented_reconstruction_says_so_in_one_line(six_frames, tmp_path):
    """Two runs of three KITTI frames that no pair joins: two models, the largest half the images."""
    from e3cm_bench.sfm.own_images import fragments

    listed = tmp_path / "pairs.txt"
    listed.write_text("000100.png 000101.png\n000101.png 000102.png\n000103.png 000104.png\n000104.png 000105.png\n")
    result = invoke("reconstruct", six_frames, "--out", tmp_path / "run", "--matcher", "sift", "--pairs", listed,
                    "--allow-disconnected")
    assert result.exit_code == 0, result.output
    said = [line for line in result.output.splitlines() if "the models fragment" in line]
    assert len(said) == 1 and "the largest holds 3 of 6 images (50%)" in said[0], result.output
    line = fragments({"n_images": 20, "largest_model_images": 3, "n_models": 4})
    assert line is not None and "3 of 20 images (15%)" in line and "\n" not in line
    assert fragments({"n_images": 20, "largest_model_images": 20, "n_models": 1}) is None


@pytest.mark.parametrize("options, mapper", [({}, "global"), ({"mapper": "incremental", "mapper_seeds": "1"},
                                                                   "incremental")])
def test_a_record_made_before_mapper_was_an_evaluation_option_still_reruns(room_run, tmp_path, options, mapper):
    """A config.yaml from before the mapper was an evaluation option loads and reruns: with no mapper
    in it (before --mapper existed) the folder is mapped with the default mapper, one seed; with the
    mapper among its dataset options (as they were recorded then), with that one."""
    out, _ = room_run
    record = yaml.safe_load((out / "config.yaml").read_text())
    for key in ("mapper", "mapper_seeds", "merge", "merge_px", "verification", "score_model"):
        record["evaluation"].pop(key, None)
    record.pop("given", None)
    record.pop("given_digest", None)
    record["dataset_load"]["options"].update(options)
    old = tmp_path / "old.yaml"
    old.write_text(yaml.safe_dump(record))
    result = invoke("rerun", old, "--out", tmp_path / "again")
    assert result.exit_code == 0, result.output
    summary = pd.read_csv(tmp_path / "again" / "summary.csv").iloc[0]
    assert summary["mapper"] == mapper and summary["mapper_seeds"] == 1 and summary["registered_images"] == 5


def test_colmaps_log_goes_to_the_run_folder_not_the_terminal(six_frames, tmp_path):
    """Keypoints merged within 8 px make COLMAP warn "Duplicate correspondence" (1699 lines here;
    26,917 with e3cm-plus on 20 frames), which scrolled the summary out of sight: now in OUT/mapper.log."""
    import subprocess
    import sys

    out = tmp_path / "run"
    # a process of its own: COLMAP writes to file descriptor 2, which the command runner does not see
    result = subprocess.run([sys.executable, "-m", "e3cm_bench", "reconstruct", str(six_frames), "--out", str(out),
                             "--matcher", "sift", "--window", "2", "--merge-px", "8"], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert "Duplicate correspondence" in (out / "mapper.log").read_text()
    terminal = result.stdout + result.stderr
    assert "Duplicate correspondence" not in terminal and "6 of 6 images registered" in terminal
