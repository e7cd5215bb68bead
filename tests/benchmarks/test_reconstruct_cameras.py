"""Where each image's intrinsics came from, per image (issue 80): EXIF where the file has a focal
length, else the reconstruction (from COLMAP's 1.2 x longer-side start), in OUT/cameras.csv."""

from __future__ import annotations

import pandas as pd
import pytest

from helpers import invoke

pytest.importorskip("pycolmap")


def test_cameras_csv_says_which_focal_came_from_exif_and_which_the_mapper_refined(tmp_path):
    from PIL import Image

    from e3cm_bench.apps.synth.multiview import write_multiview

    write_multiview(tmp_path / "room", n_views=4)
    photos = tmp_path / "photos"
    photos.mkdir()
    for k, path in enumerate(sorted((tmp_path / "room" / "images").iterdir())):
        image = Image.open(path).convert("RGB")
        exif = image.getexif()
        if k < 2:  # a 35 mm equivalent focal length of 35 mm in the first two files' EXIF
            exif.get_ifd(0x8769)[0xA405] = 35
        image.save(photos / f"{path.stem}.jpg", quality=95, exif=exif)
    run = tmp_path / "run"
    made = invoke("reconstruct", photos, "--out", run, "--matcher", "sift", "--window", 2)
    assert made.exit_code == 0, made.output
    cameras = pd.read_csv(run / "cameras.csv")
    assert list(cameras["focal_source"]) == ["exif", "exif", "reconstruction", "reconstruction"]
    guess = round(1.2 * max(Image.open(next(photos.iterdir())).size), 1)  # COLMAP's start without EXIF
    assert (cameras["focal_init_px"].iloc[2:].round(1) == guess).all()
    assert (cameras["focal_init_px"].iloc[:2].round(1) != guess).all()  # the EXIF's, by COLMAP's own rule
    registered = cameras["focal_px"].notna()
    assert registered.sum() >= 3 and (cameras.loc[registered, "focal_px"] > 0).all()
