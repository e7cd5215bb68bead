"""The embedded data: generators whose ground truth is exact (synth/)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from e3cm_bench.datasets import YFCC100M, HPatches
from e3cm_bench.matchers.sift import SiftMatcher
from e3cm_bench.geometry.metrics import epipolar_precision
from e3cm_bench.apps.synth.layouts import scene_cameras, texture_maker, write_hpatches, write_scene_pairs
from e3cm_bench.apps.synth.scene import Plane, intrinsics, look_at, relative_pose, render, room_scene
from e3cm_bench.apps.synth.textures import sample_photo


@pytest.fixture(scope="module")
def hpatches_root(tmp_path_factory):
    return write_hpatches(tmp_path_factory.mktemp("synth") / "hpatches", seed=0)


def test_photo_comes_from_the_installed_matplotlib():
    photo = sample_photo()
    assert photo.shape == (600, 512, 3) and photo.dtype == np.uint8 and photo.std() > 30


def test_hpatches_sequences_load_and_their_homographies_are_exact(hpatches_root):
    dataset = HPatches(hpatches_root)
    assert [p.name for p in dataset][:5] == ["i_hopper1/1-2", "i_hopper1/1-3", "i_hopper1/1-4", "i_hopper1/1-5", "i_hopper1/1-6"]
    assert len(dataset) == 15
    rng = np.random.default_rng(1)
    for pair in dataset:
        image0 = cv2.imread(str(pair.image0)).astype(np.float32)
        image1 = cv2.imread(str(pair.image1)).astype(np.float32)
        h, w = image0.shape[:2]
        points = np.stack([rng.uniform(20, w - 20, 400), rng.uniform(20, h - 20, 400)], 1).astype(np.float32)
        mapped = cv2.perspectiveTransform(points[None], pair.H)[0]
        inside = (mapped[:, 0] > 1) & (mapped[:, 0] < w - 2) & (mapped[:, 1] > 1) & (mapped[:, 1] < h - 2)
        here = cv2.remap(image0, points[inside, :1], points[inside, 1:], cv2.INTER_LINEAR)
        there = cv2.remap(image1, mapped[inside, :1], mapped[inside, 1:], cv2.INTER_LINEAR)
        difference = np.median(np.abs(here - there))
        if pair.name.startswith("v_"):
            # The same texture where H says: only interpolation separates the two samples.
            assert difference < 6, (pair.name, difference)
            wrong = cv2.remap(image1, points[inside, :1] + 25, points[inside, 1:], cv2.INTER_LINEAR)
            assert np.median(np.abs(here - wrong)) > 2 * difference + 4, pair.name
        else:
            assert np.array_equal(pair.H, np.eye(3))
    # The warps grow with k: v_ corners move further in later images.
    corners = np.array([[[0, 0], [383, 0], [383, 447], [0, 447]]], np.float64)
    moves = [np.abs(cv2.perspectiveTransform(corners, p.H) - corners).mean() for p in dataset if p.name.startswith("v_hopper1")]
    assert moves[-1] > moves[0] > 0


def test_generators_are_deterministic(tmp_path, hpatches_root):
    again = write_hpatches(tmp_path / "again", seed=0)
    for name in ("v_hopper2/4.ppm", "i_hopper1/6.ppm", "v_hopper1/H_1_5"):
        assert (again / name).read_bytes() == (hpatches_root / name).read_bytes(), name
    other = write_hpatches(tmp_path / "other", seed=1, n_viewpoint=1, n_illumination=0)
    assert (other / "v_hopper1/H_1_5").read_bytes() != (hpatches_root / "v_hopper1/H_1_5").read_bytes()


def test_a_reprojected_pixel_lands_on_the_same_surface_point():
    rng = np.random.default_rng(3)
    planes = room_scene(texture_maker(rng), rng)
    K = intrinsics(320, 240, 250.0)
    (R0, t0), (R1, t1) = scene_cameras(rng, strength=0.8)
    view0, view1 = render(planes, K, R0, t0, (320, 240)), render(planes, K, R1, t1, (320, 240))
    assert np.isfinite(view0.depth).mean() > 0.7 and len(np.unique(view0.plane)) >= 8  # box, stairs, walls, floor
    T = relative_pose(R0, t0, R1, t1)
    ys, xs = np.nonzero(np.isfinite(view0.depth))
    pick = rng.choice(len(xs), 3000, replace=False)
    xs, ys = xs[pick], ys[pick]
    points0 = (np.stack([xs, ys, np.ones_like(xs)], 1) @ np.linalg.inv(K).T) * view0.depth[ys, xs, None]
    points1 = points0 @ T[:3, :3].T + T[:3, 3]
    projected = points1 @ K.T
    u, v = projected[:, 0] / projected[:, 2], projected[:, 1] / projected[:, 2]
    ui, vi = np.rint(u).astype(int), np.rint(v).astype(int)
    inside = (ui >= 0) & (ui < 320) & (vi >= 0) & (vi < 240) & (points1[:, 2] > 0)
    # Visible in view 1 where its depth there is the point's own depth (occlusion handled by depth).
    visible = inside.copy()
    visible[inside] = np.abs(view1.depth[vi[inside], ui[inside]] - points1[inside, 2]) < 0.02 * points1[inside, 2]
    assert visible.mean() > 0.4 and (inside & ~visible).sum() > 0  # some points are occluded in view 1
    same_plane = view1.plane[vi[visible], ui[visible]] == view0.plane[ys[visible], xs[visible]]
    assert same_plane.mean() > 0.97  # the rest sit on plane edges, within the pixel rounding
    # Exactly the same point: the plane coordinates where it projects (sampled at the exact
    # sub-pixel position through the view-1 coordinate maps) equal those of the source pixel.
    ab1 = np.stack([cv2.remap(view1.ab[..., i].astype(np.float32), u[visible].astype(np.float32)[:, None],
                              v[visible].astype(np.float32)[:, None], cv2.INTER_LINEAR)[:, 0] for i in range(2)], 1)
    ab0 = view0.ab[ys[visible], xs[visible]]
    assert np.median(np.abs(ab1[same_plane] - ab0[same_plane])) < 1e-3


def test_plane_rejects_skewed_axes():
    with pytest.raises(ValueError, match="orthogonal"):
        Plane([0, 0, 1], [1, 0, 0], [1, 1, 0], np.zeros((4, 4, 3), np.uint8))


def test_look_at_points_the_optical_axis_at_the_target():
    R, t = look_at(np.array([1.0, -0.5, 0.0]), np.array([0.0, 0.5, 6.0]))
    assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1)
    target_cam = R @ np.array([0.0, 0.5, 6.0]) + t
    assert np.allclose(target_cam[:2], 0, atol=1e-9) and target_cam[2] > 0


def test_scene_pairs_poses_agree_with_the_images(tmp_path):
    """The pair list loads as a YFCC list, and SIFT matches on the written images satisfy the
    written relative poses: images and ground truth were made from one scene."""
    pairs_file = write_scene_pairs(tmp_path / "scenes", seed=1, n_pairs=2)
    dataset = YFCC100M(tmp_path / "scenes", pairs=pairs_file)
    assert [p.name for p in dataset] == ["room/p0_a--p0_b", "room/p1_a--p1_b"]
    sift = SiftMatcher()
    for pair in dataset:
        R = pair.T_0to1[:3, :3]
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.linalg.norm(pair.T_0to1[:3, 3]) > 0.2
        image0 = cv2.cvtColor(cv2.imread(str(pair.image0)), cv2.COLOR_BGR2RGB)
        image1 = cv2.cvtColor(cv2.imread(str(pair.image1)), cv2.COLOR_BGR2RGB)
        assert image0.shape == (480, 640, 3)
        m = sift.match(image0, image1)
        precision = epipolar_precision(m.keypoints0, m.keypoints1, pair.K0, pair.K1, pair.T_0to1)
        wrong = pair.T_0to1.copy()
        wrong[:3, :3] = cv2.Rodrigues(np.array([np.deg2rad(3.0), 0.0, 0.0]))[0] @ R  # 3 degrees of pitch off
        print(pair.name, len(m), precision)
        assert len(m) > 100 and precision[1e-4] > 0.8
        assert epipolar_precision(m.keypoints0, m.keypoints1, pair.K0, pair.K1, wrong)[1e-4] < 0.3
