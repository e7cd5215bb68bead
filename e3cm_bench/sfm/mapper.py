"""A run's matches -> a COLMAP database -> pycolmap's mapper -> the models.

The database is the export's (interchange/colmap.write_colmap): one PINHOLE camera per image
from the set's K (kept fixed: the benchmark measures the matches, not self-calibration), one
keypoint list per image in which a location that several pairs matched appears once (so that
tracks span more than two views; the protocol's merge says how near two locations must be),
and per pair the matches and a two-view geometry. The protocol's verification (protocol.py)
says which: ``estimator``, the inliers of the evaluation's own essential-matrix RANSAC
(estimators.relative_pose, the pose benchmarks' estimator, threshold and seed), so that every
matcher is judged through the same estimator; or ``colmap``, COLMAP's own verification
(pycolmap.verify_matches with hloc's options), as hloc and COLMAP's users reconstruct.

The mapper (``global``: pycolmap.global_mapping, GLOMAP; ``incremental``:
pycolmap.incremental_mapping) runs with its seed fixed (pycolmap.set_random_seed and every
options' random_seed) and one thread: COLMAP's multi-threaded parts (bundle adjustment, the
RANSACs of registration) are then deterministic, so a rerun gives the same model. Its log
(COLMAP's glog and Ceres output, stderr) goes to the workdir's mapper.log.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

# The incremental mapper's options that differ from pycolmap 4.2.1's defaults, and why; the one
# table for `sfm` (a set's ground-truth K: calibrated) and `reconstruct` (a folder's own images).
# For both:
# - min_model_size 3: COLMAP's 10 would drop every model of a small set (the synthetic scene
#   has 12 views) and the shared KITTI frames' sub-models;
# - init_min_tri_angle 4 degrees (COLMAP's 16): the initial pair must see its points under this
#   angle, which a photo collection's wide baselines give and a video's forward motion does not
#   (8 KITTI frames, each with the next 2: no model at 16, 8 of 8 registered at 4);
# - num_threads 1 (with the seed): deterministic models.
# Calibrated only (CALIBRATED_OPTIONS): intrinsics fixed (no focal, principal point or extra
# parameter refinement), since the set's K is the ground truth and a model is judged on its
# poses alone; extract_colors off, since colours need the images decoded again and change no
# number scored. `reconstruct` refines its unknown intrinsics and keeps the colours of the model
# it hands to the user.
MAPPER_OPTIONS = {"min_model_size": 3, "num_threads": 1}
MAPPER_SUB_OPTIONS = {"mapper": {"init_min_tri_angle": 4.0, "num_threads": 1}}
CALIBRATED_OPTIONS = {"ba_refine_focal_length": False, "ba_refine_principal_point": False,
                      "ba_refine_extra_params": False, "extract_colors": False}
CALIBRATED_SUB_OPTIONS = {"mapper": {"abs_pose_refine_focal_length": False, "abs_pose_refine_extra_params": False}}


def incremental_options(calibrated: bool = True) -> tuple[dict, dict]:
    """The incremental mapper's options and its {group: options} as the table above sets them."""
    if not calibrated:
        return dict(MAPPER_OPTIONS), {k: dict(v) for k, v in MAPPER_SUB_OPTIONS.items()}
    groups = {k: {**v, **CALIBRATED_SUB_OPTIONS.get(k, {})} for k, v in MAPPER_SUB_OPTIONS.items()}
    return {**MAPPER_OPTIONS, **CALIBRATED_OPTIONS}, groups


def incremental_record(calibrated: bool = True) -> dict:
    """The table as config.yaml records it: ``options``, then each group's."""
    top, groups = incremental_options(calibrated)
    return {"options": top, **groups}


# The global mapper's (GLOMAP's) options that differ from pycolmap 4.2.1's defaults: the same
# choices (intrinsics fixed in its bundle adjustment, one thread, no GPU, min_model_size 3).
GLOBAL_OPTIONS = {"min_model_size": 3, "num_threads": 1}
GLOBAL_SUB_OPTIONS = {"mapper": {"num_threads": 1},
                      "mapper.bundle_adjustment": {"refine_focal_length": False, "refine_principal_point": False,
                                                   "refine_extra_params": False},
                      "mapper.bundle_adjustment.ceres": {"use_gpu": False},
                      "mapper.global_positioning": {"use_gpu": False}}
UNCALIBRATED_GLOBAL = "mapper.bundle_adjustment"  # the group whose intrinsics reconstruct refines (pycolmap's default)


def global_groups(calibrated: bool = True) -> dict:
    """The global mapper's {group: options}; uncalibrated (reconstruct): its bundle adjustment
    refines the intrinsics as pycolmap's defaults do (the focal from EXIF or 1.2 x the longer side
    is a guess), the rest as for a calibrated set."""
    groups = {k: dict(v) for k, v in GLOBAL_SUB_OPTIONS.items()}
    if not calibrated:
        groups.pop(UNCALIBRATED_GLOBAL)
    return groups


GLOBAL_SEEDED = ("", "mapper", "mapper.rotation_averaging", "mapper.global_positioning", "mapper.retriangulation")
# COLMAP's verification as hloc runs it (hloc/reconstruction.py: at most 20000 RANSAC trials,
# inlier ratio down to 0.1); the rest is pycolmap's TwoViewGeometryOptions (4 px, 15 inliers)
# but max_H_inlier_ratio 1.0 (pycolmap's 0.8): at 0.8 COLMAP labels a pair planar or panoramic
# when its homography explains 80% of the essential matrix's inliers, which a road scene's
# forward motion does (26 of 37 KITTI SIFT pairs, window 2), and the global mapper then takes
# that pair's pose from the homography (rotation off by 2-7 degrees, translation by 50-70):
# global x merge 2 px x colmap gave SIFT AUC@10 38.5, e3cm-plus 23.4; at 1.0 (H preferred only
# where it explains more than E) 86.1 and 79.6, the incremental mapper's cells unchanged within
# 0.01 (scripts/measure/colmap_verify_global.py; docs/sfm.md "The protocol").
VERIFY_OPTIONS = {"ransac.max_num_trials": 20000, "ransac.min_inlier_ratio": 0.1, "max_H_inlier_ratio": 1.0}
DATABASE, MODELS, LOG = "database.db", "models", "mapper.log"


def mapper_settings() -> dict:
    """What config.yaml records of the reconstruction (the seed is the evaluation's; which
    mapper, merge and verification ran: the evaluation block)."""
    from e3cm_bench.ground.pycolmap import pycolmap_version

    return {
        "pycolmap": pycolmap_version(),
        "seed": "evaluation.seed + 0..mapper_seeds-1",
        "incremental": {
            "method": "pycolmap.incremental_mapping",
            **incremental_record(),
        },
        "global": global_record(),
        "verification": {
            "estimator": "the evaluation's essential-matrix RANSAC inliers (evaluation.pose_ransac_px)",
            "colmap": verification_record(),
        },
        "keypoints": "merged per image (interchange.tracks.merge_keypoints) as evaluation.merge says",
    }


def verification_record() -> dict:
    """COLMAP's verification as config.yaml records it, for sfm's ``colmap`` and for reconstruct."""
    return {"method": "pycolmap.verify_matches", "options": dict(VERIFY_OPTIONS), "seed": "evaluation.seed"}


def global_record(calibrated: bool = True) -> dict:
    """The global mapper's table as config.yaml records it."""
    return {"method": "pycolmap.global_mapping", "options": dict(GLOBAL_OPTIONS), **global_groups(calibrated)}


def _set(options, values: dict, group: str = "") -> None:
    """Set dotted-group options on a pycolmap options object (its sub-objects are copies:
    each is set back into its parent)."""
    if not group:
        for key, value in values.items():
            setattr(options, key, value)
        return
    head, _, rest = group.partition(".")
    sub = getattr(options, head)
    _set(sub, values, rest)
    setattr(options, head, sub)


def mapper_options(seed: int, mapper: str = "incremental", override: dict | None = None, calibrated: bool = True):
    """pycolmap's options of `mapper` as the benchmark sets them, seeded; `override`: more
    {dotted group: {option: value}} (a caller that refines the intrinsics, say), set last.
    calibrated=False: `reconstruct`'s (its intrinsics refined)."""
    from e3cm_bench.ground.pycolmap import pycolmap_module

    pycolmap = pycolmap_module()
    if mapper == "global":
        options = pycolmap.GlobalPipelineOptions()
        _set(options, GLOBAL_OPTIONS)
        for group, values in global_groups(calibrated).items():
            _set(options, values, group)
        for group in GLOBAL_SEEDED:
            _set(options, {"random_seed": int(seed)}, group)
    else:
        options = pycolmap.IncrementalPipelineOptions()
        top, groups = incremental_options(calibrated)
        _set(options, top)
        for group, values in groups.items():
            _set(options, values, group)
        for group in ("", "mapper", "triangulation"):
            _set(options, {"random_seed": int(seed)}, group)
    for group, values in (override or {}).items():
        _set(options, values, group)
    return options


def verify_options(seed: int):
    from e3cm_bench.ground.pycolmap import pycolmap_module

    options = pycolmap_module().TwoViewGeometryOptions()
    for key, value in VERIFY_OPTIONS.items():
        group, _, name = key.rpartition(".")
        _set(options, {name: value}, group)
    _set(options, {"random_seed": int(seed), "num_threads": 1}, "ransac")
    return options


@contextmanager
def captured_log(path: Path):
    """COLMAP's log (glog and Ceres write to the process's stderr, file descriptor 2) appended
    to `path` while the block runs; Python's own stderr is flushed around it."""
    from e3cm_bench.ground.pycolmap import pycolmap_module

    logging = pycolmap_module().logging
    before = logging.logtostderr, logging.minloglevel
    sys.stderr.flush()
    saved = os.dup(2)
    with open(path, "ab") as log:
        os.dup2(log.fileno(), 2)
        logging.logtostderr, logging.minloglevel = True, 0  # glog writes files under /tmp otherwise
        try:
            yield path
        finally:
            logging.logtostderr, logging.minloglevel = before
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)


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

    def placed(self, name0: str, name1: str, largest_only: bool = False) -> tuple:
        """Where a pair's images are: ((model, pose0), (model, pose1)) from the largest model that
        registered both (COLMAP's models may share images: max_model_overlap), else each
        image's own (model, pose) or None; the models then differ, or an image is unregistered.
        largest_only: IMC's rule, only the largest model counts (an image elsewhere: None)."""
        if largest_only:
            first = self.models[:1]
            return tuple((first[0].index, first[0].poses[n]) if first and n in first[0].poses else None
                         for n in (name0, name1))
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
    from e3cm_bench.benchmarks.pose import PoseBenchmark

    return PoseBenchmark.two_view_geometry(pair, matches, ev)


def image_size(pair, matches, side: int) -> tuple[int, int]:
    size = matches.info.get(f"size{side}")
    if size is not None:
        return tuple(int(v) for v in size)
    from e3cm_bench.ground.images import load_image

    image = load_image(pair.image0 if side == 0 else pair.image1)
    return int(image.shape[1]), int(image.shape[0])


def write_database(pairs: Sequence, matches: Sequence, ev, workdir: Path, protocol=None) -> tuple[list, dict]:
    """The database of `pairs` (each a ViewPair: view0/view1) and their `matches` (each
    correspondence once) in a fresh workdir, verified as the protocol says (a resolved
    protocol.ReconstructionProtocol; None: exact merge, the estimator's verification). Returns each pair's
    {"n_inliers", and the estimator's geometry where it ran} and the tracks' numbers
    (repeat_share, track_length_database, merge_displacement_px)."""
    from e3cm_bench.interchange import tracks
    from e3cm_bench.interchange.colmap import write_colmap
    from e3cm_bench.interchange.base import ExportItem
    from e3cm_bench.sfm.protocol import QUANTIZE_MAX_ERROR, ReconstructionProtocol
    from e3cm_bench.ground.folders import fresh_folder

    protocol = protocol or ReconstructionProtocol(merge="exact").resolved(True)
    # a rerun (--eval-only) replaces the last one's products; a link there is refused, never followed
    workdir = fresh_folder(workdir, "the reconstruction's files go there")
    items, geometries = [], []
    by_estimator = protocol.verification == "estimator"
    for pair, m in zip(pairs, matches):
        names = pair.view0, pair.view1
        found = geometry(pair, m, ev) if by_estimator and len(m) >= 5 else None
        geometries.append(found)
        items.append(ExportItem(pair.name, pair, names[0], names[1], image_size(pair, m, 0), image_size(pair, m, 1), m,
                                pair.K0, pair.K1, found))
    listed = [(item.name0, item.name1, item.matches.keypoints0, item.matches.keypoints1) for item in items]
    quantize = protocol.merge == "quantize"
    merged = tracks.merge_keypoints(listed, 0.0 if quantize else protocol.merge_px,
                                    cell=protocol.merge_px if quantize else None, max_error=QUANTIZE_MAX_ERROR)
    write_colmap(workdir, items, merged=merged)
    inliers = [int(np.count_nonzero(g["inliers"])) if g else 0 for g in geometries]
    if not by_estimator:
        inliers = colmap_verification(workdir, items, ev.seed)
    keypoints, indices = merged
    lengths = tracks.track_lengths(
        {n: len(k) for n, k in keypoints.items()}, [(a, b) for a, b, _, _ in listed], indices
    )
    radius = QUANTIZE_MAX_ERROR if quantize else protocol.merge_px
    numbers = {"repeat_share": tracks.repeat_share(listed, radius),
               "track_length_database": float(np.mean(lengths)) if len(lengths) else float("nan"),
               "merge_displacement_px": tracks.merge_displacement(listed, keypoints, indices)}
    return [{"n_inliers": n, "geometry": g} for n, g in zip(inliers, geometries)], numbers


def colmap_verification(workdir: Path, items: list, seed: int) -> list[int]:
    """pycolmap.verify_matches over the database's pairs (log in mapper.log); each pair's
    number of verified matches."""
    from e3cm_bench.ground.pycolmap import pycolmap_module
    from e3cm_bench.interchange.colmap import verify_pairs

    pycolmap = pycolmap_module()
    pycolmap.set_random_seed(int(seed))
    with captured_log(workdir / LOG):  # through pycolmap's API: no text list of names (they may hold spaces)
        verify_pairs(pycolmap, workdir / DATABASE, [(item.name0, item.name1) for item in items], verify_options(seed))
    counts = []
    with pycolmap.Database.open(str(workdir / DATABASE)) as db:
        ids = {image.name: image.image_id for image in db.read_all_images()}
        for item in items:
            id0, id1 = ids[item.name0], ids[item.name1]
            counts.append(len(db.read_two_view_geometry(id0, id1).inlier_matches)
                          if db.exists_two_view_geometry(id0, id1) else 0)
    return counts


def map_models(workdir: Path, seed: int, mapper: str = "incremental", models: str = MODELS,
               root: Path | None = None, calibrated: bool = True) -> dict:
    """The mapper on workdir's database (sfm's and reconstruct's one call), its models in
    workdir/`models`, its log appended to workdir/mapper.log; pycolmap's {index: Reconstruction}."""
    from e3cm_bench.ground.pycolmap import pycolmap_module
    from e3cm_bench.ground.folders import fresh_folder

    pycolmap = pycolmap_module()
    workdir = Path(workdir)
    models_dir = fresh_folder(workdir / models)
    pycolmap.set_random_seed(int(seed))
    run = pycolmap.global_mapping if mapper == "global" else pycolmap.incremental_mapping
    with captured_log(workdir / LOG):
        return run(str(workdir / DATABASE), str(root or workdir), str(models_dir),
                   options=mapper_options(seed, mapper, calibrated=calibrated))


def run_mapper(workdir: Path, images: list[str], seed: int, mapper: str = "incremental", models: str = MODELS,
               root: Path | None = None) -> Reconstruction:
    """map_models' models read back, largest first."""
    found = [model_of(int(index), model) for index, model in sorted(map_models(workdir, seed, mapper, models,
                                                                                 root).items())]
    # largest first (as IMC picks its model); the mapper's own index breaks ties
    found.sort(key=lambda m: (-len(m.poses), m.index))
    return Reconstruction(list(images), found, Path(workdir) / DATABASE)


def model_of(index: int, model) -> Model:
    """A pycolmap Reconstruction as a Model: each registered image's world-to-camera pose, by name,
    and its numbers (NaN track length and error without a point)."""
    poses = {}
    for image_id in model.reg_image_ids():
        image = model.image(image_id)
        pose = np.eye(4)
        pose[:3, :] = np.asarray(image.cam_from_world().matrix(), np.float64)
        poses[image.name] = pose
    points = int(model.num_points3D())
    return Model(index, poses, points, int(model.compute_num_observations()),
                 float(model.compute_mean_track_length()) if points else float("nan"),
                 float(model.compute_mean_reprojection_error()) if points else float("nan"))
