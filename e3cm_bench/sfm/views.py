"""A multi-view image set: its views (image, intrinsics, absolute pose where known) and the
pairs to match, read from one of three sources.

- a MegaDepth scene_info file (``image_paths``, ``intrinsics``, ``poses`` world-to-camera):
  every image with a path is a view, in the file's order;
- a COLMAP sparse model (``cameras`` and ``images``, text or binary, as pycolmap reads them):
  every image of the model is a view, in name order, its pose the model's cam_from_world;
- a SuperGlue-format pair list (``name0 name1 rot0 rot1 K0 K1 T_0to1``): the listed images are
  the views, known up to the relative pose of each listed pair, and the listed pairs are the
  graph (there is no absolute pose to choose other pairs by).

The first two have absolute poses, so any pair has a ground truth and the graph is a choice:
every pair (exhaustive), each image with the next K in the set's order (a sequential window),
or a list of image-name pairs.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations
from pathlib import Path

import numpy as np

from ..datasets.base import DatasetError, name_pairs
from ..datasets.truth import check_image_size, check_intrinsics, check_pose, check_quaternion, check_world_pose
from ..datasets.megadepth import PINHOLE_PARAMS, _matrix, load_scene_info

MIN_VIEWS = 2


@dataclass
class View:
    """One image of the set: its name (the path relative to the root, the COLMAP database's
    image name), its file, K of the stored image, and world-to-camera 4x4 where known."""

    name: str
    path: Path
    K: np.ndarray
    pose: np.ndarray | None = None


@dataclass
class ListedPair:
    """A pair of views to match and evaluate; T_0to1 where the source gives it directly."""

    view0: str
    view1: str
    T_0to1: np.ndarray | None = None


def _check_count(views: list[View], source: Path) -> None:
    if len(views) < MIN_VIEWS:
        raise DatasetError(f"{source}: the image set has {len(views)} image(s); a reconstruction needs at least "
                           f"{MIN_VIEWS}")


def views_from_scene_info(path: Path, root: Path) -> list[View]:
    """The views of a MegaDepth scene_info file, in its order (images without a path left out)."""
    scene = load_scene_info(path)
    views = []
    for i, image in enumerate(scene["image_paths"]):
        if image is None:
            continue
        K = _matrix(scene["intrinsics"][i], (3, 3), path, f"intrinsics[{i}]")
        check_intrinsics(K, f"{path}: intrinsics[{i}]")
        pose = _matrix(scene["poses"][i], (4, 4), path, f"poses[{i}]")
        check_world_pose(pose, f"{path}: poses[{i}]")
        views.append(View(str(image), root / str(image), K, pose))
    _check_count(views, path)
    return views


def views_from_colmap(model: Path, root: Path) -> list[View]:
    """The views of a COLMAP sparse model (cameras + images, text or binary), in name order;
    every image must be under ROOT and every camera a pinhole one without distortion (the
    matches are made on the stored images, which K must describe)."""
    from ..interchange.colmap import pycolmap_module

    pycolmap = pycolmap_module()
    model = Path(model)
    if not model.is_dir():
        raise DatasetError(f"{model}: COLMAP model folder not found")
    if not any((model / f"images.{ext}").is_file() for ext in ("bin", "txt")):
        raise DatasetError(f"{model}: holds no images.bin or images.txt (not a COLMAP sparse model)")
    try:
        reconstruction = pycolmap.Reconstruction(str(model))
    except Exception as error:  # pycolmap raises its own types for a damaged model
        raise DatasetError(f"{model}: not a readable COLMAP model ({' '.join(str(error).split())[:200]})") from None
    views = []
    for image in sorted(reconstruction.images.values(), key=lambda im: im.name):
        if not image.has_pose:
            continue  # an image the model lists but never registered has no ground truth
        views.append(View(image.name, root / image.name, *_colmap_view(reconstruction, image, model)))
    missing = [v for v in views if not v.path.is_file()]
    if missing:
        raise DatasetError(f"{model}: {len(missing)} of the {len(views)} images the model names are missing under "
                           f"{root} (first: {missing[0].name})")
    _check_count(views, model)
    return views


def _colmap_view(reconstruction, image, model: Path) -> tuple[np.ndarray, np.ndarray]:
    """K and world-to-camera 4x4 of one registered image of a COLMAP model, checked by the
    ground-truth rule (truth.py) as stored: the quaternion itself, since pycolmap turns a zero
    or non-unit one into a matrix without a word (a zero one into the identity)."""
    where = f"{model}: image {image.name}"
    camera = reconstruction.cameras[image.camera_id]
    n = PINHOLE_PARAMS.get(camera.model_name)
    params = np.asarray(camera.params, np.float64)
    if n is None or np.any(params[n:] != 0):
        raise DatasetError(f"{where} has a {camera.model_name} camera with distortion; "
                           "the set needs undistorted images and pinhole cameras")
    check_image_size(camera.width, camera.height, where)
    K = np.asarray(camera.calibration_matrix(), np.float64)
    # COLMAP's principal point is in its corner convention (top-left pixel centre at 0.5); the
    # benchmark's pixel centres are at integers, as its matches are
    K[0, 2] -= 0.5
    K[1, 2] -= 0.5
    check_intrinsics(K, where)
    cam_from_world = image.cam_from_world()
    check_quaternion(cam_from_world.rotation.quat, where)
    pose = np.eye(4)
    pose[:3, :] = np.asarray(cam_from_world.matrix(), np.float64)
    check_world_pose(pose, where)
    return K, pose


def views_from_pair_list(path: Path, root: Path) -> tuple[list[View], list[ListedPair]]:
    """The views and pairs of a SuperGlue-format list; an image named twice must have the same
    K both times (one camera per image in the reconstruction)."""
    from ..datasets.yfcc import YFCC100M
    from ..interchange.base import image_name

    listed = YFCC100M(root, pairs=path, skip_bad=False)
    views: dict[str, View] = {}
    pairs = []
    for pair in listed:
        names = []
        for image, K, where in ((pair.image0, pair.K0, "K0"), (pair.image1, pair.K1, "K1")):
            name = image_name(image, root)
            known = views.get(name)
            if known is None:
                views[name] = View(name, Path(image), np.asarray(K, np.float64))
            elif not np.allclose(known.K, K, rtol=1e-9, atol=1e-9):
                raise DatasetError(f"{path}: image {name} is listed with two different intrinsics "
                                   f"(pair {pair.name}, {where}); one image has one camera")
            names.append(name)
        if names[0] == names[1]:
            raise DatasetError(f"{path}: pair {pair.name} joins image {names[0]} with itself")
        pairs.append(ListedPair(names[0], names[1], np.asarray(pair.T_0to1, np.float64)))
    _check_count(list(views.values()), path)
    return list(views.values()), pairs


# ----------------------------------------------------------------------------- the pair graph


def exhaustive(views: list[View]) -> list[ListedPair]:
    return [ListedPair(a.name, b.name) for a, b in combinations(views, 2)]


def window(views: list[View], k: int) -> list[ListedPair]:
    """Each view with the next k in the set's order (k >= 1)."""
    return [ListedPair(views[i].name, views[j].name)
            for i in range(len(views)) for j in range(i + 1, min(i + k + 1, len(views)))]


def read_graph(path: Path, views: list[View]) -> list[ListedPair]:
    """A text list of image-name pairs (``name0 name1`` per line, # comments), each name one
    of the set's views."""
    if not Path(path).is_file():
        raise DatasetError(f"{path}: pair graph file not found")
    pairs, seen = [], set()
    for number, *names in name_pairs(path, {v.name for v in views}, "which is not an image of the set"):
        if names[0] == names[1]:
            raise DatasetError(f"{path}: line {number} joins image {names[0]} with itself")
        key = frozenset(names)
        if key in seen:
            raise DatasetError(f"{path}: line {number} lists the pair {names[0]} {names[1]} again")
        seen.add(key)
        pairs.append(ListedPair(*names))
    if not pairs:
        raise DatasetError(f"{path}: lists no pair")
    return pairs


def relative_pose(view0: View, view1: View, where: str) -> np.ndarray:
    """T_0to1 = P1 inv(P0) for world-to-camera poses, checked."""
    T = view1.pose @ np.linalg.inv(view0.pose)
    check_pose(T, where)
    return T
