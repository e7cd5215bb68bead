"""Matches of one's own images (no ground truth) -> a COLMAP database -> COLMAP's verification
-> pycolmap's mapper -> the model, written where COLMAP's GUI and hloc open it.

Where the sfm benchmark knows each image's K and keeps it fixed (sfm/mapper.py), here the
intrinsics are unknown, as for a user's photos: each image's camera as COLMAP's image reader
makes it (the focal length from EXIF where the file has it, else 1.2 x the longer side; the
principal point at the centre), shared by the images whose cameras come out the same (COLMAP's
single_camera, per size and EXIF focal), calibrated from the verified pairs' fundamental matrices
(COLMAP's view-graph calibration, as COLMAP advises before its global mapper without reliable
intrinsics) and refined by the mapper's bundle adjustment. The
rest is sfm's protocol, from the same tables: COLMAP's verification with sfm's preset
(sfm/mapper.py VERIFY_OPTIONS: pycolmap's default max_H_inlier_ratio lost a forward-moving
camera's pairs to homographies), the mapper (global or incremental) and its seeds. COLMAP's log
goes to mapper.log beside the database, not to the terminal.

The products, in the run folder: ``database.db`` (keypoints, matches, verified geometries),
``pairs.txt`` (the pair graph, ``name0 name1`` per line), ``cameras.csv`` (per image: whether its
focal length started from EXIF or from the 1.2 x guess, that start and the mapper's refined
value), ``mapper.log`` and ``sparse/N/`` per
model, largest first (``sparse/0``), in COLMAP's binary and text formats (``cameras``,
``images``, ``points3D``): ``colmap gui --import_path``, ``pycolmap.Reconstruction(path)`` and
hloc read them; with --mapper-seeds K, the same for seed + K under ``seed-K/``. A rerun
(resume, --overwrite) replaces them.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from e3cm_bench.datasets.base import pair_line
from e3cm_bench.ground.folders import remove_folder
from e3cm_bench.sfm.mapper import (LOG, Reconstruction, captured_log, colmap_verification, global_record,
                                        image_size, incremental_record, map_models, model_of, verification_record)

DATABASE, PAIRS, SPARSE, CAMERAS = "database.db", "pairs.txt", "sparse", "cameras.csv"


def settings(camera_model: str, camera_per_image: bool) -> dict:
    """What config.yaml records of the reconstruction (with the dataset; the mapper, its seeds and the
    merge radius are the evaluation's, the seed the run's): COLMAP's verification and each mapper's
    table, sfm's own (sfm/mapper.py), the intrinsics refined."""
    from e3cm_bench.ground.pycolmap import pycolmap_version

    return {"pycolmap": pycolmap_version(), "verification": verification_record(),
            "incremental": {"method": "pycolmap.incremental_mapping", **incremental_record(calibrated=False)},
            "global": global_record(calibrated=False),
            "seed": "evaluation.seed + 0..evaluation.mapper_seeds-1", "camera_model": camera_model,
            "cameras": "one per image" if camera_per_image else "shared by the images of one size and EXIF focal",
            "focal_init": "pycolmap.infer_camera_from_image: EXIF, else 1.2 x longer side; then "
                          "pycolmap.calibrate_view_graph (seeded) from the verified pairs",
            "intrinsics": "refined by the mapper"}


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
                       protocol=None, camera_model: str = "SIMPLE_RADIAL",
                       camera_per_image: bool = False) -> tuple[list[Reconstruction], list[int], list[bool]]:
    """The database of `pairs` (views.ViewPair: view0/view1 name the images under `root`) and their
    `matches` (each correspondence once), verified by COLMAP as sfm's ``colmap`` verification is
    (sfm/mapper.py: one preset), mapped by the resolved protocol's mapper (protocol.ReconstructionProtocol;
    None: the incremental mapper once, keypoints merged exactly), and written under workdir; with
    several seeds, each verifies and maps again (seed + K) under workdir/seed-K/. Returns each seed's
    reconstruction, each pair's number of verified matches (the first seed's) and whether each
    seed's view-graph calibration held (calibrate_focals)."""
    from e3cm_bench.interchange.base import ExportItem
    from e3cm_bench.interchange.colmap import write_colmap

    from e3cm_bench.sfm.protocol import ReconstructionProtocol

    protocol = protocol or ReconstructionProtocol(mapper="incremental", mapper_seeds=1, merge="exact").resolved(True)
    workdir = Path(workdir)
    for stale in (workdir / DATABASE, workdir / PAIRS, workdir / LOG, workdir / CAMERAS):
        stale.unlink(missing_ok=True)
    for stale in (workdir / SPARSE, *workdir.glob("seed-*")):
        remove_folder(stale)  # a rerun replaces the last one's products (a link there refused)
    items, images = [], []
    for pair, m in zip(pairs, matches):
        names = pair.view0, pair.view1
        images += [name for name in names if name not in images]
        items.append(ExportItem(pair.name, pair, names[0], names[1], image_size(pair, m, 0), image_size(pair, m, 1), m))
    cameras = cameras_for(root, images, camera_model, camera_per_image)
    # the pair graph for the user (reconstruct --pairs reads it back); COLMAP is handed no text list
    (workdir / PAIRS).write_text("".join(pair_line(item.name0, item.name1) for item in items))
    found, first, calibrated = [], [], []
    for s in range(protocol.mapper_seeds):
        folder = workdir if s == 0 else workdir / f"seed-{s}"
        folder.mkdir(exist_ok=True)
        write_colmap(folder, items, merge_px=protocol.merge_px, cameras=cameras)
        verified = colmap_verification(folder, items, seed + s)  # COLMAP's log: folder/mapper.log
        first = first or verified
        calibrated.append(calibrate_focals(folder, seed + s))
        found.append(_mapped(folder, images, root, seed + s, protocol.mapper))
    write_cameras(workdir / CAMERAS, cameras, refined_focals(workdir / SPARSE))
    return found, first, calibrated


def refined_focals(sparse: Path) -> dict[str, float]:
    """Each registered image's focal length (pixels, the mean of fx and fy) as the mapper refined
    it, from the largest model that holds it (sparse/0 first)."""
    from e3cm_bench.ground.pycolmap import pycolmap_module

    pycolmap = pycolmap_module()
    focals = {}
    numbered = [p for p in sparse.iterdir() if p.name.isdigit()] if sparse.is_dir() else []
    for path in sorted(numbered, key=lambda p: int(p.name)):
        model = pycolmap.Reconstruction(str(path))
        for image in model.images.values():
            focals.setdefault(image.name, model.cameras[image.camera_id].mean_focal_length())
    return focals


def write_cameras(path: Path, cameras: dict, refined: dict[str, float]) -> None:
    """cameras.csv: where each image's intrinsics came from (issue 80: EXIF where the file has a
    focal length, else the reconstruction, from a 1.2 x longer-side start), the start and the
    refined focal length (empty for an image no model registered)."""
    import pandas as pd

    pd.DataFrame([{"image": name, "focal_source": "exif" if camera.has_prior_focal_length else "reconstruction",
                   "focal_init_px": round(camera.mean_focal_length(), 3),
                   "focal_px": round(refined[name], 3) if name in refined else None}
                  for name, camera in cameras.items()]).to_csv(path, index=False)


def calibrate_focals(folder: Path, seed: int) -> bool:
    """COLMAP's view-graph calibration (pycolmap.calibrate_view_graph) on folder's verified
    database: each camera's focal length from the pairs' fundamental matrices, and the pairs'
    geometries upgraded to calibrated ones, before the mapper runs; False where too few pairs
    agree (the guess then stays). Without it the guess (1.2 x the longer side: 1489 px for the
    KITTI frames, whose focal is 718) lost most of a forward-moving camera's frames: xfeat, window
    2, registered 8 of 20 in 3 models under the incremental mapper and none under the global one;
    with it, 20 of 20 in one model under either (focal 663-675 px, refined by the mapper)."""
    from e3cm_bench.ground.pycolmap import pycolmap_module

    pycolmap = pycolmap_module()
    options = pycolmap.ViewGraphCalibrationOptions()
    options.random_seed = int(seed)
    with captured_log(folder / LOG):
        return bool(pycolmap.calibrate_view_graph(str(folder / DATABASE), options))


def _mapped(folder: Path, images: list[str], root: Path, seed: int, mapper: str) -> Reconstruction:
    """The mapper on folder's database; its models in folder/sparse/N, largest first (sparse/0, as
    a user opens it first; the mapper's index breaks ties), in COLMAP's binary and text formats."""
    mapped = map_models(folder, seed, mapper, f"{SPARSE}.mapper", root=root, calibrated=False)
    remove_folder(folder / f"{SPARSE}.mapper", ignore_errors=True)  # the mapper's snapshots
    ranked = sorted(mapped.items(), key=lambda item: (-item[1].num_reg_images(), item[0]))
    models = []
    for rank, (_, model) in enumerate(ranked):
        out = folder / SPARSE / str(rank)
        out.mkdir(parents=True)
        model.write_binary(str(out))
        model.write_text(str(out))
        models.append(model_of(rank, model))
    return Reconstruction(images, models, folder / DATABASE)
