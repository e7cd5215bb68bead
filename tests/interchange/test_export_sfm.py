"""`export --to colmap` of an sfm run: the export holds each pair's two-view geometry (the sfm
benchmark's, the pose benchmarks' RANSAC inliers, as the run's own sfm/database.db does), so
that pycolmap's own mapper reconstructs from it.

Measured (pycolmap 4.2.1, opencv SIFT, 2-core x86, the 20 shared KITTI 00 frames, --window 2):
before, the export held 0 two-view geometries and the mapper made no model; now 37 of 37, and
the mapper's largest model registers 20 of 20 frames.
"""

from __future__ import annotations

import numpy as np
import pytest

from e3cm_bench.interchange.colmap import PAIR_ID_BASE
from helpers import invoke

pycolmap = pytest.importorskip("pycolmap", reason="the colmap extra (pycolmap) is not installed")

pytestmark = pytest.mark.slow  # SIFT on 37 pairs of 1241 x 376 frames: about a minute on 2 cores


@pytest.fixture(scope="module")
def sfm_sift_run(shared_data, tmp_path_factory):
    root = shared_data / "megadepth_test_1500"
    out = tmp_path_factory.mktemp("sfm-export") / "sift"
    result = invoke("sfm", "--root", root, "--scene-info", root / "scene_info" / "kitti00_seq.npz", "--window", "2",
                    "--matcher", "sift", "--out", out)
    assert result.exit_code == 0, result.output
    return out, root


def _verified(database) -> dict[tuple[str, str], int]:
    """(image name, image name) -> distinct inliers of the two-view geometry the database holds."""
    with pycolmap.Database.open(str(database)) as db:
        names = {image.image_id: image.name for image in db.read_all_images()}
        found = {}
        for pair_id, geometry in zip(*db.read_two_view_geometries()):
            id0, id1 = divmod(int(pair_id), PAIR_ID_BASE)
            # each correspondence once: the run's database holds a pair's distinct matches, the export all
            # of them (a repeat of an inlier is an inlier), both on the same merged keypoints
            found[tuple(sorted((names[id0], names[id1])))] = len(np.unique(np.asarray(geometry.inlier_matches), axis=0))
    return found


def test_pycolmaps_mapper_reconstructs_the_export_of_an_sfm_run(sfm_sift_run, tmp_path):
    run, root = sfm_sift_run
    result = invoke("export", run, tmp_path / "colmap", "--to", "colmap")
    assert result.exit_code == 0, result.output
    assert "37 of 37 pairs with a two-view geometry" in result.output  # was 0 of 37
    exported = _verified(tmp_path / "colmap" / "database.db")
    # the same verified pairs and inliers as the reconstruction's own database
    assert exported == _verified(run / "sfm" / "database.db")
    assert len(exported) == 37 and min(exported.values()) > 0
    # pycolmap's mapper, its defaults but for two that a short forward-moving sequence needs (docs/sfm.md)
    options = pycolmap.IncrementalPipelineOptions()
    options.min_model_size = 3
    options.mapper.init_min_tri_angle = 4.0
    (tmp_path / "sparse").mkdir()
    models = pycolmap.incremental_mapping(str(tmp_path / "colmap" / "database.db"), str(root), str(tmp_path / "sparse"),
                                          options=options)
    assert models, "the mapper made no model of the export"
    assert max(model.num_reg_images() for model in models.values()) >= 18  # measured: 20 of 20
