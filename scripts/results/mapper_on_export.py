"""What COLMAP's incremental mapper makes of an exported database: how the figures of
docs/interchange.md ("Exports that reconstruct") were measured.

    e3cm-bench megadepth --root ../shared/data/megadepth_test_1500 \
        --scene-info ../shared/data/megadepth_test_1500/scene_info/kitti00_seq.npz --matcher sift --out RUN
    e3cm-bench export RUN OUT --to colmap [--merge-px R]
    python scripts/results/mapper_on_export.py OUT/database.db --images ../shared/data/megadepth_test_1500 \
        --scene-info ../shared/data/megadepth_test_1500/scene_info/kitti00_seq.npz

Prints the models, registered images, 3D points, mean track length and mean reprojection error
of the mapper's result (pycolmap.incremental_mapping under colmap.mapper_options: one thread,
seed 0, so that a rerun gives the same model; the calibration kept unless --refine-intrinsics), and, with --scene-info, the median error of the relative rotation of every
pair of images registered in the same model against the ground truth (world-to-camera poses).
"""

from __future__ import annotations

import argparse
import tempfile
from itertools import combinations
from pathlib import Path

import numpy as np

from e3cm_bench.geometry.two_view import rotation_angle_deg
from e3cm_bench.interchange.colmap import mapper_options


def figures(database: Path, images: Path, scene_info: Path | None = None, calibrated: bool = True) -> dict:
    import pycolmap

    with tempfile.TemporaryDirectory(prefix="e3cm-mapper-") as out:
        models = pycolmap.incremental_mapping(str(database), str(images), out, options=mapper_options(pycolmap, calibrated))
    found = {"models": len(models), "registered_images": 0, "points": 0, "mean_track_length": float("nan"),
             "mean_reprojection_error_px": float("nan"), "median_rotation_error_deg": float("nan"),
             "model_sizes": sorted((m.num_reg_images() for m in models.values()), reverse=True)}
    if not models:
        return found
    found["registered_images"] = sum(m.num_reg_images() for m in models.values())
    found["points"] = sum(m.num_points3D() for m in models.values())
    tracks = [p.track.length() for m in models.values() for p in m.points3D.values()]
    errors = [p.error for m in models.values() for p in m.points3D.values()]
    found["mean_track_length"] = float(np.mean(tracks)) if tracks else float("nan")
    found["mean_reprojection_error_px"] = float(np.mean(errors)) if errors else float("nan")
    if scene_info is not None:
        info = np.load(scene_info, allow_pickle=True)
        truth = {str(p): np.asarray(T, np.float64)[:3, :3] for p, T in zip(info["image_paths"], info["poses"])
                 if p is not None}
        angles = []
        for model in models.values():
            rotations = {image.name: image.cam_from_world().rotation.matrix() for image in model.images.values()
                         if image.has_pose}
            for a, b in combinations(sorted(set(rotations) & set(truth)), 2):
                angles.append(rotation_angle_deg(rotations[b] @ rotations[a].T, truth[b] @ truth[a].T))
        found["median_rotation_error_deg"] = float(np.median(angles)) if angles else float("nan")
        found["n_rotation_pairs"] = len(angles)
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("database", type=Path)
    parser.add_argument("--images", type=Path, required=True, help="the dataset root the image names are relative to")
    parser.add_argument("--scene-info", type=Path, help="a MegaDepth scene_info .npz with the images' true poses")
    parser.add_argument("--refine-intrinsics", action="store_true", help="let the mapper refine focal length, "
                        "principal point and distortion (COLMAP's default) instead of keeping the calibration")
    args = parser.parse_args()
    for key, value in figures(args.database, args.images, args.scene_info, not args.refine_intrinsics).items():
        print(f"{key}: {value:.4g}" if isinstance(value, float) else f"{key}: {value}")


if __name__ == "__main__":
    main()
