"""Parity of `e3cm-release` and `dfm` with the reference implementations on any reference file.

    python scripts/maintain/check_parity.py REF.npz A.png B.png --weights W [--perturbations 8] [--scale 1e-5]

REF.npz has the layout of ../shared/parity (see its README; keys r09_*/r095_* for the E3CM
release, dfm_* for the DFM release; lists missing from the file are skipped). A.png / B.png
are the images the reference was run on (RGB as the references read them; already resized),
W a torchvision VGG19 state dict (the file's weights). Prints each list's agreement, with the
disagreements accepted as measured ties (tests/parity.py), and exits 1 if any check fails,
2 (one line naming the key and its shape) if the file holds an array of a shape it cannot read.
A reference F stacked by OpenCV's 7-point algorithm (9x3 or 6x3) is compared by its first
solution, the one the release used.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np


def load_rgb(path: Path) -> np.ndarray:
    image = cv2.imread(str(path))
    if image is None:
        raise SystemExit(f"{path}: not an image")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("ref", type=Path)
    parser.add_argument("image0", type=Path)
    parser.add_argument("image1", type=Path)
    parser.add_argument("--weights", required=True, help="VGG19 state dict (.pth) the reference was run with")
    parser.add_argument("--perturbations", type=int, default=None, help="perturbed repeats per list (default 8)")
    parser.add_argument("--scale", type=float, default=None, help="noise, relative to each map's RMS (default 1e-5)")
    args = parser.parse_args()

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))  # parity.py: the tests' and this script's
    import parity
    from e3cm_bench.matchers import build_matcher
    from e3cm_bench.pipeline.runner import match_pair

    n = args.perturbations or parity.N_PERTURBATIONS
    if args.scale is not None:
        parity.ROUNDING_SCALE = args.scale
    ref = dict(np.load(args.ref))
    try:  # before the backbone runs: an array the checks cannot read ends the run in one line
        parity.check_reference(ref)
    except ValueError as error:
        print(f"{args.ref}: {error}", file=sys.stderr)
        return 2
    image0, image1 = load_rgb(args.image0), load_rgb(args.image1)
    checks: list[parity.ListParity] = []
    failures: list[str] = []

    if any(k.startswith("r095_") or k.startswith("r09_") for k in ref):
        matcher = build_matcher("e3cm-release", "vgg19", args.weights)
        maps0, maps1, _ = matcher.pyramids(image0, image1)
        for tag in parity.TAGS:
            if f"{tag}_L0_A" not in ref:
                continue
            checks += parity.release_levels_by_stage(maps0, maps1, ref, tag, n)
            checks += parity.release_levels_end_to_end(maps0, maps1, ref, tag, n)
            if f"{tag}_casc_A" in ref:
                cascade, out = parity.release_cascade_from_reference(ref, tag)
                checks += cascade
                for level, d in parity.fundamental_differences(out, ref, tag).items():
                    rows = len(ref[f"{tag}_F{level}"])
                    used = f" (the first of {rows // 3} stacked solutions, as the release)" if rows > 3 else ""
                    print(f"{tag} F{level} from reference lists: max |F - F_ref| = {d:.3g}{used}")
                failures += parity.fundamental_mismatches(out, ref, tag)
        if "r095_casc_A" in ref:
            m = match_pair(matcher, image0, image1, max_side=None, seed=0)
            print(parity.compare("e3cm-release end to end (cascade of our own lists)", (m.keypoints0, m.keypoints1),
                                 (ref["r095_casc_A"], ref["r095_casc_B"])).line())

    if "dfm_A" in ref:
        matcher = build_matcher("dfm", "vgg19", args.weights)
        pyramid = lambda image: matcher.backbone.pyramid(matcher.network_input(image), stage1_tap=True)  # noqa: E731
        (feats0, _), (feats1, _) = pyramid(image0), pyramid(image1)
        stage0 = parity.dfm_stage0(feats0[-1], feats1[-1], len(feats0) - 1, ref, n)
        if stage0["same_H"]:
            verdict = "identical" if stage0["same_entries"] else (
                f"identical to {stage0['H_px']:.2g} px (entries differ: OpenCV's refinement rounds per OpenBLAS kernel)")
        else:
            verdict = f"differs (by up to {stage0['H_px']:.3g} px)"
        print(f"dfm stage 0: {stage0['stage0_matches']} mutual NN, H_init {verdict}"
              f"{' (a measured tie)' if stage0['tie'] else ''}")
        if not stage0["same_H"] and not stage0["tie"]:
            failures.append("dfm stage 0: H_init differs and no perturbation changes the stage-0 list")
        checks.append(parity.dfm_stage1(pyramid, image0, image1, ref["dfm_Hinit"], ref,
                                        "dfm stage 1 from reference H_init", n)[0])
        if stage0["same_H"]:  # after a stage-0 tie the warp differs: the stages stand for the end to end
            checks.append(parity.dfm_stage1(pyramid, image0, image1, stage0["H"], ref, "dfm end to end", n)[0])

    for check in checks:
        print(check.line())
        if not check.passed:
            failures.append(check.what)
    print(f"{len(checks) - sum(not c.passed for c in checks)} of {len(checks)} lists at parity"
          + (f"; failed: {', '.join(failures)}" if failures else ""))
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
