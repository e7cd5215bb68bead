"""The sfm benchmark end to end: pycolmap's mapper on the benchmark's database of a SIFT run over
the shared KITTI 00 frames, a rerun's identical numbers, the set forms (scene_info, COLMAP model,
pair list), bad input in one line, and a mapper that finds nothing recorded as a result.

Measured (pycolmap 4.2.1, opencv SIFT, 2-core x86): the first 8 KITTI frames with a window of 2
(13 pairs) register 8 of 8 images in one model; the margins below would not survive a database
whose tracks do not chain (every track two views: no model) or a wrong pose convention (errors
of tens of degrees).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from e3cm_bench.benchmarks import EvalSettings, get_benchmark
from e3cm_bench.datasets.base import DatasetError
from e3cm_bench.sfm.views import ViewPair
from e3cm_bench.datasets.megadepth import load_scene_info
from e3cm_bench.ground.matches import Matches
from helpers import invoke, kitti_frames, one_line_error

pycolmap = pytest.importorskip("pycolmap", reason="the sfm benchmark needs pycolmap (the colmap extra)")

KITTI = "megadepth_test_1500"
SCENE_INFO = "megadepth_test_1500/scene_info/kitti00_seq.npz"


@pytest.fixture(scope="module")
def kitti(shared_data, tmp_path_factory) -> tuple[Path, Path]:
    """(root, scene_info) of the first 8 KITTI 00 frames: a scene_info written from the shared
    one with the other images' paths left out (None), so the set stays small."""
    return shared_data / KITTI, kitti_frames(shared_data, 8, tmp_path_factory.mktemp("kitti8") / "kitti00_first8.npz")


def kitti_args(kitti) -> list:
    root, scene_info = kitti
    return ["sfm", "--root", root, "--scene-info", scene_info, "--window", "2", "--matcher", "sift"]


@pytest.fixture(scope="module")
def sift_run(kitti, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sfm") / "sift"
    result = invoke(*kitti_args(kitti), "--out", out)
    assert result.exit_code == 0, result.output
    return out


def test_mapper_registers_kitti_frames_from_the_benchmark_database(sift_run):
    summary = pd.read_csv(sift_run / "summary.csv").iloc[0]
    per_pair = pd.read_csv(sift_run / "per_pair.csv")
    assert summary["n_pairs"] == 13 and summary["n_images"] == 8
    # measured: 8 of 8 in one model, AUC@10 about 85
    assert summary["registered_images"] >= 7, summary.to_dict()
    assert summary["n_models"] >= 1 and summary["points"] > 200
    assert summary["mean_track_length"] > 2.5  # tracks chain over more than two views
    assert 0 < summary["mean_reprojection_error"] < 1.5
    assert summary["auc@10"] > 50 and summary["maa"] > 0.5
    for column in ("auc@10_lo", "auc@10_hi", "maa_lo", "maa_hi"):
        assert np.isfinite(summary[column])
    assert summary["auc@10_lo"] <= summary["auc@10"] <= summary["auc@10_hi"]
    assert list(per_pair.columns) == ["pair", "bag", "n_matches", "n_duplicates", "n_inliers", "registered0", "registered1",
                                      "model", "err_R", "err_t", "err_pose",
                                      *(f"{c}_s{s}" for s in range(3) for c in ("model", "err_R", "err_t", "err_pose"))]
    # the first seed's columns are the plain ones; the headline is the mean over the 3 seeds
    assert per_pair["err_pose"].equals(per_pair["err_pose_s0"])
    # the benchmark's own database is one pycolmap reads, and the mapper registers images from it again
    database = sift_run / "sfm" / "database.db"
    with pycolmap.Database.open(str(database)) as db:
        assert db.num_images() == 8
    model = pycolmap.Reconstruction(str(next((sift_run / "sfm" / "models").iterdir())))
    assert model.num_reg_images() >= 7
    config = (sift_run / "config.yaml").read_text()
    assert "min_model_size: 3" in config and "pair_graph: window 2" in config


def test_rerun_gives_identical_numbers(kitti, sift_run):
    """--eval-only reruns the whole reconstruction (database, mapper) from the cached matches."""
    before = [(sift_run / name).read_text() for name in ("summary.csv", "per_pair.csv")]
    models = sorted(p.name for p in (sift_run / "sfm" / "models").iterdir())
    result = invoke(*kitti_args(kitti), "--out", sift_run, "--eval-only")
    assert result.exit_code == 0, result.output
    assert [(sift_run / name).read_text() for name in ("summary.csv", "per_pair.csv")] == before
    assert sorted(p.name for p in (sift_run / "sfm" / "models").iterdir()) == models


def test_table_and_compare_read_sfm_runs(sift_run, tmp_path):
    result = invoke("table", sift_run, sift_run, "--out", tmp_path / "table")
    assert result.exit_code == 0, result.output
    table = pd.read_csv(tmp_path / "table.csv")
    assert {"auc@10", "mAA", "registered_images", "n_models", "auc@10_lo"} <= set(table.columns)
    result = invoke("compare", sift_run, sift_run)
    assert result.exit_code == 0, result.output
    assert "err_pose" in result.output


# ----------------------------------------------------------------------------- set forms


def _colmap_model(folder: Path, views: list[tuple[str, np.ndarray, np.ndarray]]) -> Path:
    """A sparse model (text) with one PINHOLE camera and the given (name, K, world-to-camera)."""
    model = pycolmap.Reconstruction()
    for index, (name, K, pose) in enumerate(views, 1):
        camera = pycolmap.Camera(model="PINHOLE", width=1241, height=376, camera_id=index,
                                 params=[K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5])
        model.add_camera_with_trivial_rig(camera)
        image = pycolmap.Image(name=name, camera_id=index, image_id=index)
        model.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(pose[:3, :3]), pose[:3, 3]))
    folder.mkdir(parents=True)
    model.write_text(str(folder))
    return folder


def test_colmap_model_gives_the_scene_info_pairs(shared_data, tmp_path):
    root = shared_data / KITTI
    scene = load_scene_info(shared_data / SCENE_INFO)
    views = [(str(scene["image_paths"][i]), scene["intrinsics"][i], scene["poses"][i]) for i in range(4)]
    model = _colmap_model(tmp_path / "model", views)
    bench = get_benchmark("sfm")
    from_model = bench.load_dataset(root, colmap_model=model)
    from_scene = bench.load_dataset(root, scene_info=shared_data / SCENE_INFO, graph=_graph(tmp_path, views))
    assert len(from_model) == 6 == len(from_scene)
    for a, b in zip(from_model, from_scene):
        assert a.view0 == b.view0 and a.view1 == b.view1
        # COLMAP stores a rotation as a quaternion: KITTI's 7-digit, not quite orthonormal matrices move by 1e-5
        np.testing.assert_allclose(a.T_0to1, b.T_0to1, atol=1e-4)
        np.testing.assert_allclose(a.K0, b.K0, atol=1e-9)


def _graph(tmp_path: Path, views) -> Path:
    path = tmp_path / "graph.txt"
    names = [name for name, _, _ in views]
    path.write_text("".join(f"{a} {b}\n" for i, a in enumerate(names) for b in names[i + 1:]))
    return path


def test_window_and_exhaustive_graphs(shared_data):
    bench = get_benchmark("sfm")
    root, scene_info = shared_data / KITTI, shared_data / SCENE_INFO
    assert len(bench.load_dataset(root, scene_info=scene_info)) == 190  # 20 frames, every pair
    window = bench.load_dataset(root, scene_info=scene_info, window="3")
    assert len(window) == 19 + 18 + 17
    assert window[0].name == "kitti00_seq/000100--000101"
    for bad, match in ((dict(window="0"), "--window must be from 1 to 10000"),
                       (dict(window="2", graph=scene_info), "two pair graphs")):
        with pytest.raises(DatasetError, match=match):
            bench.load_dataset(root, scene_info=scene_info, **bad)


# ----------------------------------------------------------------------------- bad input


def test_one_image_is_one_line(shared_data, tmp_path):
    scene = load_scene_info(shared_data / SCENE_INFO)
    paths = np.array(scene["image_paths"], dtype=object)
    paths[1:] = None
    one = tmp_path / "one.npz"
    np.savez(one, image_paths=paths, intrinsics=scene["intrinsics"], poses=scene["poses"], pair_infos=scene["pair_infos"])
    line = one_line_error(invoke("sfm", "--root", shared_data / KITTI, "--scene-info", one, "--matcher", "sift",
                                 "--out", tmp_path / "out"))
    assert str(one) in line and "1 image" in line


def test_scene_info_without_poses_is_one_line(shared_data, tmp_path):
    scene = load_scene_info(shared_data / SCENE_INFO)
    bad = tmp_path / "noposes.npz"
    np.savez(bad, image_paths=scene["image_paths"], intrinsics=scene["intrinsics"], pair_infos=scene["pair_infos"])
    line = one_line_error(invoke("sfm", "--root", shared_data / KITTI, "--scene-info", bad, "--matcher", "sift",
                                 "--out", tmp_path / "out"))
    assert str(bad) in line and "poses" in line


def test_colmap_model_with_missing_images_is_one_line(shared_data, tmp_path):
    scene = load_scene_info(shared_data / SCENE_INFO)
    views = [(f"absent/{i}.png", scene["intrinsics"][i], scene["poses"][i]) for i in range(3)]
    model = _colmap_model(tmp_path / "model", views)
    (tmp_path / "images").mkdir()
    line = one_line_error(invoke("sfm", "--root", tmp_path / "images", "--colmap-model", model, "--matcher", "sift",
                                 "--out", tmp_path / "out"))
    assert str(model) in line and "missing" in line and "absent/0.png" in line


def _numbers(*arrays) -> list[str]:
    return [str(v) for a in arrays for v in np.ravel(a).tolist()]


def test_pair_list_with_two_intrinsics_for_one_image_is_one_line(shared_data, tmp_path):
    scene = load_scene_info(shared_data / SCENE_INFO)
    root = shared_data / KITTI
    names = [str(p) for p in scene["image_paths"][:3]]
    K = scene["intrinsics"][0]
    other = K.copy()
    other[0, 0] += 10
    T = np.eye(4)
    T[2, 3] = 1.0
    lines = [" ".join([names[0], names[1], "0", "0", *_numbers(K, K, T)]),
             " ".join([names[0], names[2], "0", "0", *_numbers(other, K, T)])]
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("\n".join(lines) + "\n")
    line = one_line_error(invoke("sfm", "--root", root, "--pairs", pairs, "--matcher", "sift", "--out", tmp_path / "out"))
    assert str(pairs) in line and names[0] in line and "intrinsics" in line


def test_pair_list_set_reads_relative_poses(shared_data, tmp_path):
    scene = load_scene_info(shared_data / SCENE_INFO)
    root = shared_data / KITTI
    names = [str(p) for p in scene["image_paths"][:3]]
    K, poses = scene["intrinsics"], scene["poses"]
    lines = []
    for i, j in ((0, 1), (1, 2)):
        T = poses[j] @ np.linalg.inv(poses[i])
        lines.append(" ".join([names[i], names[j], "0", "0", *_numbers(K[i], K[j], T)]))
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("\n".join(lines) + "\n")
    dataset = get_benchmark("sfm").load_dataset(root, pairs=pairs)
    assert len(dataset) == 2 and len(dataset.views) == 3
    with pytest.raises(DatasetError, match="--window and --graph apply"):
        get_benchmark("sfm").load_dataset(root, pairs=pairs, window="2")


def test_mapper_without_a_model_is_a_recorded_result(shared_data, tmp_path):
    """Matches that agree with no geometry: the mapper finds no model, every pair fails, 0 registered."""
    scene = load_scene_info(shared_data / SCENE_INFO)
    root = shared_data / KITTI
    rng = np.random.default_rng(0)
    pairs, matches = [], []
    names = [str(p) for p in scene["image_paths"][:4]]
    for i in range(4):
        for j in range(i + 1, 4):
            T = scene["poses"][j] @ np.linalg.inv(scene["poses"][i])
            pairs.append(ViewPair(f"s/{i}--{j}", root / names[i], root / names[j], K0=scene["intrinsics"][i],
                                  K1=scene["intrinsics"][j], T_0to1=T, view0=names[i], view1=names[j]))
            points = rng.uniform([0, 0], [1240, 375], (2, 0 if (i, j) == (0, 1) else 200, 2))  # one pair: no match
            matches.append(Matches(points[0], points[1], None, {"size0": (1241, 376), "size1": (1241, 376)}))
    rows, numbers = get_benchmark("sfm").evaluate_set(pairs, matches, EvalSettings(), tmp_path)
    assert numbers["registered_images"] == 0 and numbers["n_models"] == 0 and numbers["points"] == 0
    assert all(row["err_pose"] == float("inf") and row["model"] == -1 for row in rows)
    assert rows[0]["n_matches"] == 0 and rows[0]["n_inliers"] == 0
    summary = get_benchmark("sfm").summarize(rows, EvalSettings())
    assert summary["n_failures"] == 6 and summary["auc@10"] == 0 and summary["maa"] == 0
