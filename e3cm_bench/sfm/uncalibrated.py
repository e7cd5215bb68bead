"""Matches of one's own images (no ground truth) -> a COLMAP database -> COLMAP's verification
-> pycolmap's incremental mapper -> the model, written where COLMAP's GUI and hloc open it.

Where the sfm benchmark knows each image's K and keeps it fixed (sfm/mapper.py), here the
intrinsics are unknown, as for a user's photos: each image's camera as COLMAP's image reader
makes it (the focal length from EXIF where the file has it, else 1.2 x the longer side; the
principal point at the centre), shared by the images whose cameras come out the same (COLMAP's
single_camera, per size and EXIF focal), and refined by the mapper's bundle adjustment. Without K there is no essential
matrix to check the
matches with, so COLMAP verifies them itself (pycolmap.verify_matches: its fundamental /
essential / homography RANSAC, seeded), as hloc's pipelines do, and the mapper runs on its
inliers.

The products, in the run folder: ``database.db`` (keypoints, matches, verified geometries),
``pairs.txt`` (the pair graph, ``name0 name1`` per line) and ``sparse/N/`` per model, largest
first (``sparse/0``), in COLMAP's binary and text formats (``cameras``, ``images``, ``points3D``): ``colmap gui
--import_path``,
``pycolmap.Reconstruction(path)`` and hloc read them. A rerun (resume, --overwrite) replaces them.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from e3cm_bench.datasets.base import pair_line
from e3cm_bench.storage.folder import fresh_folder, remove_folder
from e3cm_bench.sfm.mapper import Reconstruction, image_size, incremental_record, mapper_options, model_of

DATABASE, PAIRS, SPARSE = "database.db", "pairs.txt", "sparse"


def settings(camera_model: str, camera_per_image: bool, merge_px: float | None) -> dict:
    """What config.yaml records of the reconstruction (with the dataset; the seed is the run's)."""
    from e3cm_bench.ground.pycolmap import pycolmap_version

    return {"method": "pycolmap.verify_matches + pycolmap.incremental_mapping", "pycolmap": pycolmap_version(),
            **incremental_record(calibrated=False),
            "seed": "evaluation.seed", "camera_model": camera_model,
            "cameras": "one per image" if camera_per_image else "shared by the images of one size and EXIF focal",
            "focal_init": "pycolmap.infer_camera_from_image: EXIF, else 1.2 x longer side",
            "intrinsics": "refined by the mapper",
            "merge_px": merge_px}


def cameras_for(root: Path, names: Sequence[str], camera_model: str, camera_per_image: bool) -> dict:
    """Each image's camera as COLMAP's image reader makes it (pycolmap.infer_camera_from_image:
    the focal length from EXIF where the file has it, else 1.2 x the longer side; the principal
    point at the centre); unless camera_per_image, images whose cameras come out the same (size,
    model, parameters, whether the focal is a prior) share one object, so one camera."""
    from e3cm_bench.ground.pycolmap import pycolmap_module

    pycolmap = pycolmap_module()
    options = pycolmap.ImageReaderOptions()
    options.camera_model = camera_model
    cameras, shared = {}, {}
    for name in names:
        camera = pycolmap.infer_camera_from_image(str(Path(root) / name), options)
        key = (camera.model_name, camera.width, camera.height, tuple(np.round(camera.params, 9)),
               camera.has_prior_focal_length)
        cameras[name] = camera if camera_per_image else shared.setdefault(key, camera)
    return cameras


def reconstruct_images(pairs: Sequence, matches: Sequence, workdir: Path, root: Path, seed: int = 0,
                       merge_px: float = 0.0, camera_model: str = "SIMPLE_RADIAL",
                       camera_per_image: bool = False) -> tuple[Reconstruction, list[int]]:
    """The database of `pairs` (views.ViewPair: view0/view1 name the images under `root`) and their
    `matches` (each correspondence once), verified by COLMAP, mapped, and written under workdir;
    returns the reconstruction and each pair's number of verified matches."""
    from e3cm_bench.ground.pycolmap import pycolmap_module
    from e3cm_bench.interchange.colmap import verify_pairs, write_colmap
    from e3cm_bench.interchange.base import ExportItem

    pycolmap = pycolmap_module()
    workdir = Path(workdir)
    for stale in (workdir / DATABASE, workdir / PAIRS):
        stale.unlink(missing_ok=True)
    remove_folder(workdir / SPARSE)  # a rerun replaces the last one's products (a link there refused)
    items, images = [], []
    for pair, m in zip(pairs, matches):
        names = pair.view0, pair.view1
        images += [name for name in names if name not in images]
        items.append(ExportItem(pair.name, pair, names[0], names[1], image_size(pair, m, 0), image_size(pair, m, 1), m))
    write_colmap(workdir, items, merge_px=merge_px, cameras=cameras_for(root, images, camera_model, camera_per_image))
    # the pair graph for the user (reconstruct --pairs reads it back); COLMAP is handed no text list
    (workdir / PAIRS).write_text("".join(pair_line(item.name0, item.name1) for item in items))
    pycolmap.set_random_seed(int(seed))
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 1  # its progress log is thousands of lines; warnings and errors still show
    try:
        verification = pycolmap.TwoViewGeometryOptions()
        verification.ransac.random_seed = int(seed)
        verify_pairs(pycolmap, workdir / DATABASE, [(item.name0, item.name1) for item in items], verification)
        verified = _verified(pycolmap, workdir / DATABASE, items)
        mapper_out = workdir / f"{SPARSE}.mapper"  # where the mapper writes its snapshots
        fresh_folder(mapper_out)
        found = pycolmap.incremental_mapping(str(workdir / DATABASE), str(root), str(mapper_out),
                                             options=mapper_options(seed, calibrated=False))
    finally:
        pycolmap.logging.minloglevel = level
    remove_folder(mapper_out, ignore_errors=True)
    # sparse/0 is the largest model (the mapper's index breaks ties), as a user opens it first
    ranked = sorted(found.items(), key=lambda item: (-item[1].num_reg_images(), item[0]))
    models = []
    for rank, (_, model) in enumerate(ranked):
        folder = workdir / SPARSE / str(rank)
        folder.mkdir(parents=True)
        model.write_binary(str(folder))
        model.write_text(str(folder))
        models.append(model_of(rank, model))
    return Reconstruction(images, models, workdir / DATABASE), verified


def _verified(pycolmap, database: Path, items) -> list[int]:
    """Each pair's number of matches COLMAP's verification kept (0: none, or no geometry)."""
    db = pycolmap.Database.open(str(database))
    try:
        ids = {image.name: image.image_id for image in db.read_all_images()}
        return [len(db.read_two_view_geometry(ids[i.name0], ids[i.name1]).inlier_matches)
                if db.exists_two_view_geometry(ids[i.name0], ids[i.name1]) else 0 for i in items]
    finally:
        db.close()
