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

import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from itertools import combinations
from pathlib import Path, PurePosixPath
from typing import Iterator

import numpy as np

from e3cm_bench.datasets.base import DatasetError, Pair, name_pairs
from e3cm_bench.datasets.truth import check_image_size, check_intrinsics, check_pose, check_quaternion, check_world_pose
from e3cm_bench.datasets.megadepth import PINHOLE_PARAMS, _matrix, load_scene_info
from e3cm_bench.datasets.yfcc import YFCC100M

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


@dataclass
class ViewPair(Pair):
    """A pair of a multi-view set, as the evaluation that maps the set needs it: the names of its
    two images in the set (the reconstruction's image names), the bag (the pair graph's connected
    component, 0 the largest) it belongs to, and, for a folder of one's own images, where its images
    lie and how their cameras are modelled (`setup`: own_images.FolderSetup), the same object for every
    pair of a set. The reconstruction's protocol is the evaluation's (sfm/protocol.py protocol_of)."""

    view0: str = ""
    view1: str = ""
    bag: int = 0
    setup: object = field(default=None, repr=False)


def _check_count(views: list[View], source: Path) -> None:
    if len(views) < MIN_VIEWS:
        raise DatasetError(f"{source}: the image set has {len(views)} image(s); a reconstruction needs at least "
                           f"{MIN_VIEWS}")


def image_key(image: str | Path, root: Path, anywhere: bool, where: str) -> str:
    """An image's name in the set (the database's image name, the key of its view): its path
    under ROOT, '/'-separated, with '.' and '..' resolved as text (links not followed, so that
    `a/../b.png` and `b.png` are one image). An image outside the root (an absolute path
    elsewhere, a '..' that leaves it) is refused unless `anywhere` (--absolute-paths): then every
    image is named by its absolute path."""
    full = Path(os.path.normpath(Path(root, image).absolute()))
    if anywhere:
        return full.as_posix()
    try:
        return full.relative_to(os.path.normpath(Path(root).absolute())).as_posix()
    except ValueError:
        raise DatasetError(f"{where}: image {image} lies outside the image root {root}; name images by their path "
                           "under --root, or pass --absolute-paths to take images from anywhere") from None


def _once(views: list[View], source: Path, entries: list[str] | None = None) -> list[View]:
    """The views, each image once: two views of one image would be two database images.
    entries: where the source lists each view (named in the error)."""
    first: dict[str, int] = {}
    for i, view in enumerate(views):
        if view.name in first:
            where = f" ({entries[first[view.name]]} and {entries[i]})" if entries else ""
            raise DatasetError(f"{source}: image {view.name} is listed twice{where}; each image is one view of the set")
        first[view.name] = i
    return views


def views_from_scene_info(path: Path, root: Path, anywhere: bool = False) -> list[View]:
    """The views of a MegaDepth scene_info file, in its order (images without a path left out)."""
    scene = load_scene_info(path)
    views, entries = [], []
    for i, image in enumerate(scene["image_paths"]):
        if image is None:
            continue
        entries.append(f"image_paths[{i}]")
        K = _matrix(scene["intrinsics"][i], (3, 3), path, f"intrinsics[{i}]")
        check_intrinsics(K, f"{path}: intrinsics[{i}]")
        pose = _matrix(scene["poses"][i], (4, 4), path, f"poses[{i}]")
        check_world_pose(pose, f"{path}: poses[{i}]")
        name = image_key(str(image), root, anywhere, f"{path}: image_paths[{i}]")
        views.append(View(name, Path(name) if anywhere else root / name, K, pose))
    _check_count(views, path)
    return _once(views, path, entries)


def views_from_colmap(model: Path, root: Path, anywhere: bool = False) -> list[View]:
    """The views of a COLMAP sparse model (cameras + images, text or binary), in name order;
    every image must be under ROOT and every camera a pinhole one without distortion (the
    matches are made on the stored images, which K must describe)."""
    from e3cm_bench.ground.pycolmap import pycolmap_module

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
        name = image_key(image.name, root, anywhere, f"{model}: image {image.name}")
        views.append(View(name, Path(name) if anywhere else root / name, *_colmap_view(reconstruction, image, model)))
    missing = [v for v in views if not v.path.is_file()]
    if missing:
        raise DatasetError(f"{model}: {len(missing)} of the {len(views)} images the model names are missing under "
                           f"{root} (first: {missing[0].name})")
    _check_count(views, model)
    return _once(views, model)


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


class _PairLines(YFCC100M):
    """YFCC100M's reading of a SuperGlue-format list without its PairList checks: the set names
    its pairs itself (a stereo layout, image_0/N.png and image_1/N.png, repeats the file stems
    YFCC's pair names are made of) and checks its images once (MultiViewSet)."""

    def __init__(self, root: Path, pairs: Path) -> None:  # no PairList.__init__: the set checks its pairs
        self.root, self.pairs_file = Path(root), Path(pairs)


def views_from_pair_list(path: Path, root: Path, anywhere: bool = False
                         ) -> tuple[list[View], list[ListedPair], list[tuple[str, str]]]:
    """The views and pairs of a SuperGlue-format list, and (pair, problem) of its pairs whose
    ground truth is unusable; an image named twice must have the same K both times (one camera
    per image in the reconstruction)."""
    listed, bad = _PairLines(root, path).read_pairs()
    views: dict[str, View] = {}
    pairs = []
    for pair in listed:
        names = []
        for image, K, where in ((pair.image0, pair.K0, "K0"), (pair.image1, pair.K1, "K1")):
            name = image_key(image, root, anywhere, f"{path}: pair {pair.name}")
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
    if views or not bad:  # a list of bad pairs only is refused with their problem (PairList)
        _check_count(list(views.values()), path)
    return list(views.values()), pairs, bad


# ----------------------------------------------------------------------------- the pair graph


def exhaustive(views: list[View]) -> Iterator[ListedPair]:
    """Every pair, made as they are taken (graph_size counts them first)."""
    return (ListedPair(a.name, b.name) for a, b in combinations(views, 2))


def window(views: list[View], k: int) -> Iterator[ListedPair]:
    """Each view with the next k in the set's order (k >= 1), made as they are taken."""
    return (ListedPair(views[i].name, views[j].name)
            for i in range(len(views)) for j in range(i + 1, min(i + k + 1, len(views))))


def graph_size(n_views: int, k: int | None = None) -> int:
    """The number of pairs of `exhaustive` (k None) or `window(k)` over n_views views, without making them."""
    if k is None or k >= n_views - 1:
        return n_views * (n_views - 1) // 2
    return k * (n_views - k) + k * (k - 1) // 2


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


def components(edges: Iterable[tuple[str, str]]) -> list[list[str]]:
    """The connected components of the graph of these image pairs: each a list of image names
    in the order first met, largest first (equal sizes: the one met first, first)."""
    parent: dict[str, str] = {}

    def root(name: str) -> str:
        while parent[name] != name:
            parent[name] = parent[parent[name]]  # path halving: near-flat trees on long chains
            name = parent[name]
        return name

    for a, b in edges:
        for name in (a, b):
            parent.setdefault(name, name)
        ra, rb = root(a), root(b)
        if ra != rb:
            parent[rb] = ra
    groups: dict[str, list[str]] = {}
    for name in parent:  # insertion order: first met
        groups.setdefault(root(name), []).append(name)
    return sorted(groups.values(), key=len, reverse=True)  # sorted() is stable: ties keep their order


def pair_labels(views: list[View]) -> dict[str, str]:
    """Each view's part of a pair's name: its file stem where no two views share one (the names
    runs have had), else its name without the suffix (a stereo layout: image_0/N, image_1/N),
    else its whole name; never with a leading '/' (an absolute name: the cache's groups)."""
    for label in (lambda n: PurePosixPath(n).stem, lambda n: str(PurePosixPath(n).with_suffix("")), str):
        labels = {v.name: label(v.name).lstrip("/") for v in views}
        if len(set(labels.values())) == len(labels):
            return labels
    raise DatasetError(f"{views[0].path}: two images of the set have one name")  # views are unique by name


def relative_pose(view0: View, view1: View, where: str) -> np.ndarray:
    """T_0to1 = P1 inv(P0) for world-to-camera poses, checked."""
    T = view1.pose @ np.linalg.inv(view0.pose)
    check_pose(T, where)
    return T
