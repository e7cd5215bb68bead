"""The DFM release's output on one pair, for a parity fixture (the `dfm_*` keys of ../shared/parity).

    python scripts/maintain/dfm_release_fixture.py RELEASE_PYTHON_DIR A.png B.png OUT.npz

RELEASE_PYTHON_DIR is the `python/` folder of a checkout of ufukefe/DFM, whose
`DeepFeatureMatcher.py` runs unmodified: only torchvision's `vgg19(pretrained=True)`, which would
download ImageNet weights, is answered with the fixtures' seed-0 VGG19
(`torch.manual_seed(0); torchvision.models.vgg19(weights=None)`). As ../shared/parity/README.md
says: `DeepFeatureMatcher(model VGG19, enable_two_stage=True, ratio_th=[0.9]*4 + [0.95, 1.0]).match`
with `cv2.setRNGSeed(0)` before it; A and B read as RGB. Writes dfm_A, dfm_B (N x 2, pixels of
the images given), dfm_Hinit and dfm_H. On graf12_640 it gives the shared fixture's four arrays
bit for bit.
"""

from __future__ import annotations

import sys

import cv2
import numpy as np


def main() -> int:
    if len(sys.argv) != 5:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    release, path_a, path_b, out = sys.argv[1:]
    import torch
    import torchvision

    torch.manual_seed(0)
    seed0 = torchvision.models.vgg19(weights=None)
    sys.path.insert(0, release)
    import DeepFeatureMatcher as reference  # the release's module, as it is

    reference.models.vgg19 = lambda pretrained=True, **kwargs: seed0
    matcher = reference.DeepFeatureMatcher(model="VGG19", device=torch.device("cpu"), enable_two_stage=True,
                                           ratio_th=[0.9, 0.9, 0.9, 0.9, 0.95, 1.0], bidirectional=True)
    a, b = (cv2.cvtColor(cv2.imread(p), cv2.COLOR_BGR2RGB) for p in (path_a, path_b))
    cv2.setRNGSeed(0)
    with torch.no_grad():
        H, H_init, points_a, points_b = matcher.match(a, b, 0)
    np.savez(out, dfm_A=points_a.T.astype(np.float64), dfm_B=points_b.T.astype(np.float64), dfm_Hinit=H_init, dfm_H=H)
    print(f"{out}: {points_a.shape[1]} matches")
    return 0


if __name__ == "__main__":
    sys.exit(main())
