"""The demo's room scene (scene.room_scene) rendered from many views, for the sfm benchmark.

The cameras stand on an arc across the front of the room, each looking at the box and the
staircase from a little further right than the one before, so neighbouring views overlap
much and the ends of the arc little (about 3 degrees of viewing change between neighbours,
about 30 across the arc). The truth is exact: the renderer's K and world-to-camera poses.
Written in the MegaDepth scene_info layout (``scene_info/room_multiview.npz``: image_paths,
intrinsics, poses, pair_infos for neighbouring views; images under ``images/``), so that
``e3cm-bench sfm --root ROOT --scene-info ROOT/scene_info/room_multiview.npz`` reads it.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from e3cm_bench.ground.files import write_atomically
from e3cm_bench.apps.synth.layouts import SCENE_SIZE, _write_rgb, seeded_room
from e3cm_bench.apps.synth.scene import look_at, render

GENERATOR_VERSION = 1  # bump when the written data changes, so cached copies are rebuilt
SCENE_INFO = "scene_info/room_multiview.npz"


def arc_cameras(n_views: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """World-to-camera (R, t) of n_views cameras on the arc, left to right."""
    cameras = []
    for i in range(n_views):
        s = i / max(n_views - 1, 1)
        centre = np.array([-1.6 + 3.2 * s, -0.1 + 0.15 * np.sin(np.pi * s), 0.4 + 0.6 * np.sin(np.pi * s)])
        target = np.array([-0.8 + 1.6 * s, 0.7, 6.5])
        cameras.append(look_at(centre, target))
    return cameras


def write_multiview(root: str | Path, n_views: int = 10, seed: int = 0) -> Path:
    """Images and the scene_info file under `root` (reused when written with the same
    settings); returns the scene_info path."""
    if n_views < 2:
        raise ValueError(f"a multi-view set needs at least 2 views, got {n_views}")
    root = Path(root)
    path = root / SCENE_INFO
    stamp = {"generator": GENERATOR_VERSION, "seed": seed, "views": n_views}
    stamp_file = root / "generated.json"
    if path.is_file() and stamp_file.is_file() and json.loads(stamp_file.read_text()) == stamp:
        return path
    _, planes, K = seeded_room(seed)
    names, poses = [], []
    for i, (R, t) in enumerate(arc_cameras(n_views)):
        name = f"images/view{i:02d}.png"
        _write_rgb(root / name, render(planes, K, R, t, SCENE_SIZE).image)
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = R, t
        names.append(name)
        poses.append(pose)
    pair_infos = np.empty(n_views - 1, dtype=object)
    for i in range(n_views - 1):
        pair_infos[i] = ((i, i + 1), 1.0, np.zeros(0))
    arrays = {"image_paths": np.array(names), "intrinsics": np.stack([K] * n_views), "poses": np.stack(poses),
              "pair_infos": pair_infos}

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)

    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomically(path, write)
    write_atomically(stamp_file, lambda tmp: tmp.write_text(json.dumps(stamp)))
    return path
