"""`e3cm-bench match`: two images (or the built-in demo pair) through a matcher."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.markup import escape

from e3cm_bench.backbones.names import BACKBONES, DEFAULT_BACKBONE, OFFLINE_BACKBONE
from e3cm_bench.cli.common import (app, console, method_option, method_values, warn, MatcherOpt, WeightsOpt, DeviceOpt,
                                   EstimatorOpt, SampsonOpt, RatioOpt, SetOpt, PrecisionOpt, ChannelOrderOpt,
                                   friendly_errors)


# match's own words for two method options (declared in options.METHOD_OPTIONS)
MatchMaxSideOpt = method_option("max_side", help="Resize so the longer side is at most N px (0 or none: full "
                                                 "resolution).")
MatchSeedOpt = method_option("seed", help="Seed of the robust estimators inside the matcher.")


@app.command()
@friendly_errors
def match(
    image0: Annotated[Optional[Path],
                      typer.Argument(help="First image (omit both for the built-in demo pair).")] = None,
    image1: Annotated[Optional[Path], typer.Argument(help="Second image.")] = None,
    matcher: MatcherOpt = "e3cm",
    # its default depends on the images (the demo pair's needs no download), hence None here
    backbone: Annotated[Optional[str], typer.Option("--backbone",
                                                    help=f"One of: {', '.join(BACKBONES)} (default "
                                                         f"{DEFAULT_BACKBONE}, the paper's: its ImageNet weights "
                                                         f"download once; {OFFLINE_BACKBONE} needs no download, and "
                                                         "the demo pair uses it).")] = None,
    weights: WeightsOpt = None,
    max_side: MatchMaxSideOpt = None,
    device: DeviceOpt = "cpu",
    estimator: EstimatorOpt = None,
    sampson_px: SampsonOpt = None,
    ratio: RatioOpt = None,
    seed: MatchSeedOpt = 0,
    out: Annotated[Path, typer.Option("--out", help="Output folder.")] = Path("e3cm-match"),
    settings: SetOpt = None,
    precision: PrecisionOpt = "fp32",
    channel_order: ChannelOrderOpt = "rgb",
    verbose: Annotated[bool, typer.Option("--verbose", "-v",
                                          help="Also print how the memory allocator was set up (a run folder's "
                                               "config.yaml records it as environment.allocator).")] = False,
) -> None:
    """Match two images: writes OUT/matches.npz and OUT/matches.png, prints counts and stage times."""
    from e3cm_bench.ground.devices import keep_freed_memory
    from e3cm_bench.ground.locks import writable_folder
    from e3cm_bench.method.spec import build_method
    from e3cm_bench.pipeline.runner import match_pair

    if (image0 is None) != (image1 is None):
        raise ValueError("give two images, or none for the built-in demo pair")
    writable_folder(out, create=False)  # before any work: a folder that cannot take the results is one line now
    img0, img1, H, backbone = _images(image0, image1, backbone)
    # no benchmark: the one path without one (the side as given, 0 or none: full resolution)
    method = build_method(method_values(dict(matcher=matcher, backbone=backbone, weights=weights, max_side=max_side,
                                       estimator=estimator, sampson_px=sampson_px, ratio=ratio, seed=seed,
                                       settings=settings, precision=precision, channel_order=channel_order)),
                          None, device, warn=warn)
    kept = keep_freed_memory()  # the second image's pass reuses the first's pages, as in a run (docs/speed.md)
    t = time.perf_counter()
    m = method.build(device)
    t_load = time.perf_counter() - t
    result = match_pair(m, img0, img1, method.max_side, method.seed_for_matching)
    _write_and_say(result, img0, img1, H, method, matcher, out)
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


def _images(image0: Path | None, image1: Path | None, backbone: str | None):
    """The two images, the demo pair's homography (None for the user's images) and the backbone:
    the given one, else the offline one for the demo pair and the paper's for the user's."""
    from e3cm_bench.ground.images import load_image
    from e3cm_bench.apps.synth.textures import demo_pair

    if image0 is None:
        img0, img1, H = demo_pair()
        backbone = backbone or OFFLINE_BACKBONE
        console.print(f"demo: a procedural 640x480 scene and its warp by a known homography; backbone {backbone}")
        return img0, img1, H, backbone
    return load_image(image0), load_image(image1), None, backbone or DEFAULT_BACKBONE


def _write_and_say(result, img0, img1, H, method, matcher: str, out: Path) -> None:
    """OUT/matches.npz and OUT/matches.png (green/red by the demo pair's ground truth), and the count."""
    from e3cm_bench.benchmarks import get_benchmark
    from e3cm_bench.datasets.base import Pair
    from e3cm_bench.pipeline.evaluate import drawn
    from e3cm_bench.ground.files import save_npz
    from e3cm_bench.ground.locks import writable_folder
    from e3cm_bench.matchers import get_matcher
    from e3cm_bench.drawing.matches import draw_matches, save_image

    k0, k1 = result.keypoints0, result.keypoints1
    writable_folder(out)
    save_npz(out / "matches.npz", keypoints0=k0, keypoints1=k1, scores=result.scores)
    correct = None
    shown = drawn(result)  # each correspondence once, as the evaluation scores them (matches.npz keeps all)
    if H is not None:
        hpatches = get_benchmark("hpatches")  # scored as an HPatches run without --protocol is
        correct = hpatches.correct_mask(Pair("demo", Path(), Path(), H=H), shown, hpatches.resolve_eval())
    save_image(out / "matches.png", draw_matches(img0, img1, shown.keypoints0, shown.keypoints1, correct=correct,
                                                 max_lines=500))
    console.print(f"[bold]{len(k0)} matches[/] ({escape(get_matcher(matcher).name)}, "
                  f"{escape(str(method.backbone or 'no backbone'))}) -> {escape(str(out))}/matches.npz, matches.png")
    if correct is not None:
        console.print(f"demo ground truth: {correct.mean() * 100 if len(correct) else 0:.1f}% of matches within 3 px")

