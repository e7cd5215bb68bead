"""`e3cm-bench match`: two images (or the built-in demo pair) through a matcher."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated, Optional

import typer

from ..backbone_names import BACKBONES, DEFAULT_BACKBONE, OFFLINE_BACKBONE
from .common import app, console, MatcherOpt, WeightsOpt, DeviceOpt, EstimatorOpt, SampsonOpt, RatioOpt, SetOpt, PrecisionOpt, ChannelOrderOpt, parse_settings, friendly_errors


@app.command()
@friendly_errors
def match(
    image0: Annotated[Optional[Path], typer.Argument(help="First image (omit both for the built-in demo pair).")] = None,
    image1: Annotated[Optional[Path], typer.Argument(help="Second image.")] = None,
    matcher: MatcherOpt = "e3cm",
    backbone: Annotated[Optional[str], typer.Option("--backbone", help=f"One of: {', '.join(BACKBONES)} (default {DEFAULT_BACKBONE}, the paper's: its ImageNet weights download once; {OFFLINE_BACKBONE} needs no download, and the demo pair uses it).")] = None,
    weights: WeightsOpt = None,
    max_side: Annotated[Optional[int], typer.Option("--max-side", help="Resize so the longer side is at most N px.")] = None,
    device: DeviceOpt = "cpu",
    estimator: EstimatorOpt = None,
    sampson_px: SampsonOpt = None,
    ratio: RatioOpt = None,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the robust estimators inside the matcher.")] = 0,
    out: Annotated[Path, typer.Option("--out", help="Output folder.")] = Path("e3cm-match"),
    settings: SetOpt = None,
    precision: PrecisionOpt = "fp32",
    channel_order: ChannelOrderOpt = "rgb",
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Also print how the memory allocator was set up (a run folder's config.yaml records it as environment.allocator).")] = False,
) -> None:
    """Match two images: writes OUT/matches.npz and OUT/matches.png, prints counts and stage times."""
    from ..benchmarks import EvalSettings, get_benchmark
    from ..datasets.base import Pair
    from ..devices import keep_freed_memory
    from ..evaluate import drawn
    from ..files import save_npz, writable_folder
    from ..images import load_image
    from ..matchers import get_matcher
    from ..method import MethodSpec, parse_numbers
    from ..runner import match_pair
    from ..synth.textures import demo_pair
    from ..viz import draw_matches, save_image

    if (image0 is None) != (image1 is None):
        raise ValueError("give two images, or none for the built-in demo pair")
    writable_folder(out, create=False)  # before any work: a folder that cannot take the results is one line now
    H = None
    if image0 is None:
        img0, img1, H = demo_pair()
        backbone = backbone or OFFLINE_BACKBONE
        console.print(f"demo: a procedural 640x480 scene and its warp by a known homography; backbone {backbone}")
    else:
        img0, img1 = load_image(image0), load_image(image1)
        backbone = backbone or DEFAULT_BACKBONE
    method = MethodSpec.create(
        matcher, backbone, weights, estimator, parse_numbers(sampson_px, "--sampson-px"),
        parse_numbers(ratio, "--ratio"), max_side or None, seed,
        options=parse_settings(settings, precision, channel_order, device) if get_matcher(matcher, allow_import=True).needs_backbone else parse_settings(settings),
    )
    kept = keep_freed_memory()  # the second image's pass reuses the first's pages, as in a run (docs/speed.md)
    t = time.perf_counter()
    m = method.build(device)
    t_load = time.perf_counter() - t
    result = match_pair(m, img0, img1, method.max_side, method.seed_for_matching)
    k0, k1 = result.keypoints0, result.keypoints1

    writable_folder(out)
    save_npz(out / "matches.npz", keypoints0=k0, keypoints1=k1, scores=result.scores)
    correct = None
    shown = drawn(result)  # each correspondence once, as the evaluation scores them (matches.npz keeps all)
    if H is not None:
        correct = get_benchmark("hpatches").correct_mask(Pair("demo", Path(), Path(), H=H), shown, EvalSettings())
    save_image(out / "matches.png", draw_matches(img0, img1, shown.keypoints0, shown.keypoints1, correct=correct,
                                                 max_lines=500))

    console.print(f"[bold]{len(k0)} matches[/] ({get_matcher(matcher).name}, {method.backbone or 'no backbone'}) -> {out}/matches.npz, matches.png")
    if correct is not None:
        console.print(f"demo ground truth: {correct.mean() * 100 if len(correct) else 0:.1f}% of matches within 3 px")
    info = result.info
    if "counts_before" in info:
        levels = sorted(info["counts_before"], reverse=True)
        console.print("matches per level (after refinement -> after epipolar rejection): " + ", ".join(
            f"L{l}: {info['counts_before'][l]}->{info['counts_after'][l]}" for l in levels))
        for level, note in sorted(info.get("rejection", {}).items(), reverse=True):
            if note != "applied":
                console.print(f"level {level}: rejection {note}")
    timings = {"model load": t_load, **info.get("timings", {})}
    console.print("time per stage (s): " + ", ".join(f"{k} {v:.3f}" for k, v in timings.items()))
    if verbose:  # a developer's detail (docs/speed.md), not a user's: runs keep it in config.yaml
        console.print(f"allocator: {kept}", markup=False)


