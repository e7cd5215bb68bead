"""A run's matches -> a COLMAP database -> pycolmap's incremental mapper -> the models.

The database is the export's (interchange/colmap.write_colmap): one PINHOLE camera per image
from the set's K (kept fixed: the benchmark measures the matches, not self-calibration), one
keypoint list per image in which a location that several pairs matched appears once (so that
tracks span more than two views), and per pair the matches and a two-view geometry holding
the inliers of the evaluation's own essential-matrix RANSAC (estimators.relative_pose, the
pose benchmarks' estimator, threshold and seed). The mapper then needs no verification of its
own, so every matcher is judged through the same estimator.

The mapper runs with its seed fixed (pycolmap.set_random_seed and the options' random_seed,
the evaluation's --seed) and one thread: COLMAP's multi-threaded parts (bundle adjustment, the
RANSACs of registration) are then deterministic, so a rerun gives the same model.
"""

from __future__ import annotations

import shutil
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

# The incremental mapper's options that differ from pycolmap 4.2.1's defaults, and why:
# - min_model_size 3: COLMAP's 10 would drop every model of a small set (the synthetic scene
#   has 12 views) and the shared KITTI frames' sub-models;
# - intrinsics fixed (no focal, principal point or extra parameter refinement): the set's K
#   is the ground truth, so a model is judged on its poses alone;
# - init_min_tri_angle 4 degrees (COLMAP's 16): the initial pair must see its points under this
#   angle, which a photo collection's wide baselines give and a video's forward motion does not
#   (8 KITTI frames, each with the next 2: no model at 16, 8 of 8 registered at 4);
# - extract_colors off: colours need the images decoded again and change no number here;
# - num_threads 1 (with the seed): deterministic models.
MAPPER_OPTIONS = {
    "min_model_size": 3,
    "ba_refine_focal_length": False,
    "ba_refine_principal_point": False,
    "ba_refine_extra_params": False,
    "extract_colors": False,
    "num_threads": 1,
}
MAPPER_SUB_OPTIONS = {"mapper": {"init_min_tri_angle": 4.0, "abs_pose_refine_focal_length": False,
                                 "abs_pose_refine_extra_params": False, "num_threads": 1}}
DATABASE, MODELS = "database.db", "models"


def mapper_settings() -> dict:
    """What config.yaml records of the reconstruction (the seed is the evaluation's)."""
    from ..interchange.colmap import pycolmap_module

    try:
        version = pycolmap_module().__version__
    except ValueError:
        version = None
    return {"method": "pycolmap.incremental_mapping", "pycolmap": version, "options": dict(MAPPER_OPTIONS),
            **{k: dict(v) for k, v in MAPPER_SUB_OPTIONS.items()}, "seed": "evaluation.seed",
            "two_view_geometry": "the evaluation's essential-matrix RANSAC inliers (evaluation.pose_ransac_px)",
            "keypoints": "merged per image (interchange.tracks.merge_keypoints): exact repeats, and within "
                         "dataset.merge_px pixels where it is above 0"}


def mapper_options(seed: int):
    from ..interchange.colmap import pycolmap_module

    pycolmap = pycolmap_module()
    options = pycolmap.IncrementalPipelineOptions()
    for key, value in MAPPER_OPTIONS.items():
        setattr(options, key, value)
    for group, values in MAPPER_SUB_OPTIONS.items():
        sub = getattr(options, group)
        for key, value in values.items():
            setattr(sub, key, value)
        setattr(options, group, sub)
    options.random_seed = int(seed)
    options.mapper.random_seed = int(seed)
    options.triangulation.random_seed = int(seed)
    return options


@dataclass
class Model:
    """One reconstructed model: the world-to-camera pose of each registered image, by name."""

    index: int
    poses: dict[str, np.ndarray]
    points: int
    observations: int
    mean_track_length: float
    mean_reprojection_error: float


@dataclass
class Reconstruction:
    """The mapper's outcome over a set: its models (largest first) and the set's images."""

    images: list[str]
    models: list[Model] = field(default_factory=list)
    database: Path | None = None

    def where(self, name: str) -> tuple[int, np.ndarray] | None:
        """(model index, world-to-camera 4x4) of a registered image, else None."""
        for model in self.models:
            if name in model.poses:
                return model.index, model.poses[name]
        return None

    def placed(self, name0: str, name1: str) -> tuple:
        """Where a pair's images are: ((model, pose0), (model, pose1)) from the largest model that
        registered both (COLMAP's models may share images: max_model_overlap), else each
        image's own (model, pose) or None; the models then differ, or an image is unregistered."""
        for model in self.models:
            if name0 in model.poses and name1 in model.poses:
                return (model.index, model.poses[name0]), (model.index, model.poses[name1])
        return self.where(name0), self.where(name1)

    def numbers(self) -> dict:
        """The set's numbers: images, registered, models, points, mean track length and mean
        reprojection error (both over all models' observations; NaN without a point)."""
        registered = {name for model in self.models for name in model.poses}
        points = sum(m.points for m in self.models)
        observations = sum(m.observations for m in self.models)
        # a model without a point (COLMAP keeps one whose points were all filtered) adds nothing
        error = (sum(m.mean_reprojection_error * m.observations for m in self.models if m.observations) / observations
                 if observations else float("nan"))
        return {"n_images": len(self.images), "registered_images": len(registered), "n_models": len(self.models),
                "points": points, "mean_track_length": observations / points if points else float("nan"),
                "mean_reprojection_error": float(error)}


def geometry(pair, matches, ev) -> dict | None:
    """The evaluation's own relative pose on these matches and its inliers (export's rule, with
    the pose benchmarks' RANSAC threshold)."""
    from ..benchmarks.pose import PoseBenchmark
    from ..interchange.export import estimate_geometry

    return estimate_geometry(PoseBenchmark, pair, matches, ev)


def image_size(pair, matches, side: int) -> tuple[int, int]:
    size = matches.info.get(f"size{side}")
    if size is not None:
        return tuple(int(v) for v in size)
    from ..images import load_image

    image = load_image(pair.image0 if side == 0 else pair.image1)
    return int(image.shape[1]), int(image.shape[0])


def reconstruct(pairs: Sequence, matches: Sequence, ev, workdir: Path, root: Path | None = None,
                merge_px: float = 0.0) -> tuple[Reconstruction, list]:
    """Write the database of `pairs` (each with meta view0/view1) and their `matches` (each
    correspondence once) under workdir, run the mapper, and read its models back. Returns the
    reconstruction and each pair's two-view geometry (None where the estimate failed)."""
    from ..interchange.colmap import pycolmap_module, write_colmap
    from ..interchange.export import ExportItem

    pycolmap = pycolmap_module()
    workdir = Path(workdir)
    if workdir.is_symlink() or workdir.exists() and not workdir.is_dir():
        raise ValueError(f"{workdir}: is not a folder (the reconstruction's files go there); move it away and rerun")
    if workdir.exists():
        shutil.rmtree(workdir)  # a rerun (--eval-only) replaces the last one's products
    workdir.mkdir(parents=True)
    items, geometries, images = [], [], []
    for pair, m in zip(pairs, matches):
        names = pair.meta["view0"], pair.meta["view1"]
        for name in names:
            if name not in images:
                images.append(name)
        found = geometry(pair, m, ev) if len(m) >= 5 else None
        geometries.append(found)
        items.append(ExportItem(pair.name, pair, names[0], names[1], image_size(pair, m, 0), image_size(pair, m, 1), m,
                                pair.K0, pair.K1, found))
    write_colmap(workdir, items, merge_px=merge_px)
    models_dir = workdir / MODELS
    models_dir.mkdir()
    pycolmap.set_random_seed(int(ev.seed))
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 1  # its progress log is thousands of lines; warnings and errors still show
    try:
        found_models = pycolmap.incremental_mapping(str(workdir / DATABASE), str(root or workdir), str(models_dir),
                                                    options=mapper_options(ev.seed))
    finally:
        pycolmap.logging.minloglevel = level
    models = []
    for index, model in sorted(found_models.items()):
        poses = {}
        for image_id in model.reg_image_ids():
            image = model.image(image_id)
            pose = np.eye(4)
            pose[:3, :] = np.asarray(image.cam_from_world().matrix(), np.float64)
            poses[image.name] = pose
        points = int(model.num_points3D())
        models.append(Model(int(index), poses, points, int(model.compute_num_observations()),
                            float(model.compute_mean_track_length()) if points else float("nan"),
                            float(model.compute_mean_reprojection_error()) if points else float("nan")))
    # largest first (as IMC picks its model); the mapper's own index breaks ties
    models.sort(key=lambda m: (-len(m.poses), m.index))
    return Reconstruction(images, models, workdir / DATABASE), geometries
