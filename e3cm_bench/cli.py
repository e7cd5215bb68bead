"""e3cm-bench command line: one thin function per subcommand."""

from __future__ import annotations

import functools
import os
import sys
import time
from pathlib import Path
from typing import Annotated, Optional

import cv2
import numpy as np
import torch
import typer
from rich.console import Console

from . import geometry
from .backbones import BACKBONES, BackboneError
from .datasets.base import DatasetError
from .datasets.synthetic import demo_pair
from .experiments import make_dataset, matcher_settings, run_method, write_table
from .experiments import reproduce as reproduce_experiment
from .matchers import MATCHERS, NEEDS_BACKBONE, build_matcher
from .images import load_image, resize_max_side, to_original_pixels
from .matching.cascade import ESTIMATORS
from .viz import draw_matches, save_image

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="Training-free deep feature matching (E3CM, DFM, SIFT+NN) and the HPatches / MegaDepth-1500 / YFCC100M benchmarks.",
)
console = Console()
err_console = Console(stderr=True)

# Options shared by `match` and the benchmark commands.
MatcherOpt = Annotated[str, typer.Option("--matcher", help=f"One of: {', '.join(MATCHERS)}.")]
BackboneOpt = Annotated[str, typer.Option("--backbone", help=f"One of: {', '.join(BACKBONES)}.")]
WeightsOpt = Annotated[Optional[Path], typer.Option("--weights", help="Local state-dict file for the backbone (instead of the ImageNet download).")]
DeviceOpt = Annotated[str, typer.Option("--device", help="cpu, cuda or mps.")]
EstimatorOpt = Annotated[str, typer.Option("--cascade-estimator", help=f"F per level: {', '.join(ESTIMATORS)} (top8 = the paper).")]
SampsonOpt = Annotated[Optional[str], typer.Option("--sampson-px", help="Sampson thresholds in pixels for levels 0,1,2,3, comma-separated.")]
RatioOpt = Annotated[Optional[str], typer.Option("--ratio", help="Ratio-test thresholds for levels 0..4, comma-separated.")]
LabelOpt = Annotated[Optional[str], typer.Option("--label", help="Method name in tables and plots (default: matcher[-backbone]).")]


def _floats(text: str | None, option: str) -> tuple[float, ...] | None:
    if text is None:
        return None
    try:
        return tuple(float(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"{option}: expected comma-separated numbers, got {text!r}") from None


def _matcher_settings(matcher: str, estimator: str, sampson_px: str | None, ratio: str | None) -> dict:
    return matcher_settings(matcher, estimator, _floats(sampson_px, "--sampson-px"), _floats(ratio, "--ratio"))


def friendly_errors(command):
    """Bad input ends in one line on stderr and a non-zero exit, never a traceback.

    E3CM_BENCH_DEBUG=1 lets the exception through with its traceback (for developers).
    """

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            return command(*args, **kwargs)
        except (DatasetError, BackboneError, ValueError, FileNotFoundError, KeyError) as exc:
            if os.environ.get("E3CM_BENCH_DEBUG"):
                raise
            message = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            err_console.print(f"[bold red]error:[/] {message}", highlight=False, soft_wrap=True)
            raise typer.Exit(2) from None
        except KeyboardInterrupt:
            err_console.print("[yellow]interrupted[/]: matches written so far are kept; rerun the same command to resume")
            raise typer.Exit(130) from None

    return wrapper


@app.command()
@friendly_errors
def match(
    image0: Annotated[Optional[Path], typer.Argument(help="First image (omit both for the built-in demo pair).")] = None,
    image1: Annotated[Optional[Path], typer.Argument(help="Second image.")] = None,
    matcher: MatcherOpt = "e3cm",
    backbone: Annotated[Optional[str], typer.Option("--backbone", help=f"One of: {', '.join(BACKBONES)} (default vgg19; the demo uses efficientnet_lite0, which needs no download).")] = None,
    weights: WeightsOpt = None,
    max_side: Annotated[Optional[int], typer.Option("--max-side", help="Resize so the longer side is at most N px.")] = None,
    device: DeviceOpt = "cpu",
    cascade_estimator: EstimatorOpt = "top8",
    sampson_px: SampsonOpt = None,
    ratio: RatioOpt = None,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the robust estimators inside the matcher.")] = 0,
    out: Annotated[Path, typer.Option("--out", help="Output folder.")] = Path("e3cm-match"),
) -> None:
    """Match two images: writes OUT/matches.npz and OUT/matches.png, prints counts and stage times."""
    if (image0 is None) != (image1 is None):
        raise ValueError("give two images, or none for the built-in demo pair")
    H = None
    if image0 is None:
        img0, img1, H = demo_pair()
        backbone = backbone or "efficientnet_lite0"
        console.print(f"demo: a procedural 640x480 scene and its warp by a known homography; backbone {backbone}")
    else:
        img0, img1 = load_image(image0), load_image(image1)
        backbone = backbone or "vgg19"
    t = time.perf_counter()
    m = build_matcher(matcher, backbone, str(weights) if weights else None, device,
                      settings=_matcher_settings(matcher, cascade_estimator, sampson_px, ratio))
    t_load = time.perf_counter() - t
    small0, s0 = resize_max_side(img0, max_side)
    small1, s1 = resize_max_side(img1, max_side)
    cv2.setRNGSeed(seed)  # cascade RANSAC and DFM's homography: the same matches on every run
    result = m.match(small0, small1)
    k0, k1 = to_original_pixels(result.keypoints0, s0), to_original_pixels(result.keypoints1, s1)

    out.mkdir(parents=True, exist_ok=True)
    np.savez(out / "matches.npz", keypoints0=k0, keypoints1=k1, scores=result.scores)
    correct = None
    if H is not None:
        correct = np.linalg.norm(geometry.warp_points(H, k0) - k1, axis=1) <= 3.0
    save_image(out / "matches.png", draw_matches(img0, img1, k0, k1, correct=correct, max_lines=500))

    console.print(f"[bold]{len(k0)} matches[/] ({m.name}, {backbone if matcher in NEEDS_BACKBONE else 'no backbone'}) -> {out}/matches.npz, matches.png")
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


def _benchmark_command(benchmark: str, dataset_options: dict, opts: dict) -> None:
    torch.manual_seed(opts["seed"])
    dataset = make_dataset(benchmark, opts["root"], skip_missing=opts["skip_missing"], **dataset_options)
    n_total = len(dataset) + dataset.n_skipped
    console.print(
        f"{benchmark}: {len(dataset)} pairs"
        + (f" ({dataset.n_skipped} of {n_total} skipped: images missing)" if dataset.n_skipped else "")
        + (f", limited to the first {opts['limit']}" if opts["limit"] else "")
    )
    run_method(
        benchmark, dataset, opts["out"], matcher=opts["matcher"], backbone=opts["backbone"],
        weights=str(opts["weights"]) if opts["weights"] else None, device=opts["device"],
        settings=_matcher_settings(opts["matcher"], opts["cascade_estimator"], opts["sampson_px"], opts["ratio"]),
        max_side=opts["max_side"], limit=opts["limit"], seed=opts["seed"], overwrite=opts["overwrite"],
        eval_only=opts["eval_only"], viz=opts["viz"], label=opts["label"], ransac_px=opts["ransac_px"], console=console,
    )


# Options of the three benchmark commands.
RootOpt = Annotated[Path, typer.Option("--root", help="Dataset root folder.")]
OutOpt = Annotated[Path, typer.Option("--out", help="Run folder (config.yaml, matches.h5, CSVs, plots).")]
MaxSideOpt = Annotated[Optional[int], typer.Option("--max-side", help="Longer image side for matching (0 = full resolution).")]
LimitOpt = Annotated[Optional[int], typer.Option("--limit", help="Only the first N pairs.")]
SeedOpt = Annotated[int, typer.Option("--seed", help="Seed of every RANSAC (set before each pair).")]
OverwriteOpt = Annotated[bool, typer.Option("--overwrite", help="Discard matches already in --out.")]
EvalOnlyOpt = Annotated[bool, typer.Option("--eval-only", help="Recompute the metrics from matches.h5 without matching.")]
VizOpt = Annotated[int, typer.Option("--viz", help="Draw the first N pairs (green: correct by ground truth, red: not).")]
SkipMissingOpt = Annotated[bool, typer.Option("--skip-missing", help="Evaluate only pairs whose images exist.")]
CompareOpt = Annotated[bool, typer.Option("--compare/--no-compare", help="Difference columns (measured - paper); off for data other than the paper's benchmark.")]
RansacOpt = Annotated[Optional[float], typer.Option("--ransac-px", help="Threshold of the evaluation RANSAC in px (HPatches 3, pose 0.5).")]


@app.command()
@friendly_errors
def hpatches(
    root: RootOpt, out: OutOpt, matcher: MatcherOpt = "e3cm", backbone: BackboneOpt = "vgg19", weights: WeightsOpt = None,
    max_side: MaxSideOpt = None, limit: LimitOpt = None, device: DeviceOpt = "cpu", seed: SeedOpt = 0,
    overwrite: OverwriteOpt = False, eval_only: EvalOnlyOpt = False, viz: VizOpt = 0,
    cascade_estimator: EstimatorOpt = "top8", sampson_px: SampsonOpt = None, ratio: RatioOpt = None, label: LabelOpt = None,
    exclude_large: Annotated[bool, typer.Option("--exclude-large", help="The 108-sequence / 540-pair protocol (D2-Net).")] = False,
    sequences: Annotated[Optional[list[str]], typer.Option("--sequences", help="Keep these sequences (names or globs; repeatable).")] = None,
    skip_missing: SkipMissingOpt = False, ransac_px: RansacOpt = None,
) -> None:
    """HPatches: MMA@1..10 px (overall / illumination / viewpoint) and homography accuracy."""
    _benchmark_command("hpatches", {"exclude_large": exclude_large, "sequences": sequences}, locals())


@app.command()
@friendly_errors
def megadepth(
    root: RootOpt, out: OutOpt, matcher: MatcherOpt = "e3cm", backbone: BackboneOpt = "vgg19", weights: WeightsOpt = None,
    max_side: MaxSideOpt = None, limit: LimitOpt = None, device: DeviceOpt = "cpu", seed: SeedOpt = 0,
    overwrite: OverwriteOpt = False, eval_only: EvalOnlyOpt = False, viz: VizOpt = 0,
    cascade_estimator: EstimatorOpt = "top8", sampson_px: SampsonOpt = None, ratio: RatioOpt = None, label: LabelOpt = None,
    scene_info: Annotated[Optional[list[Path]], typer.Option("--scene-info", help="scene_info .npz files (default: all under ROOT/scene_info).")] = None,
    skip_missing: SkipMissingOpt = False, ransac_px: RansacOpt = None,
) -> None:
    """MegaDepth-1500: relative pose AUC@5/10/20 and matching precision."""
    _benchmark_command("megadepth", {"scene_info": scene_info}, locals())


@app.command()
@friendly_errors
def yfcc(
    root: RootOpt, out: OutOpt, matcher: MatcherOpt = "e3cm", backbone: BackboneOpt = "vgg19", weights: WeightsOpt = None,
    max_side: MaxSideOpt = None, limit: LimitOpt = None, device: DeviceOpt = "cpu", seed: SeedOpt = 0,
    overwrite: OverwriteOpt = False, eval_only: EvalOnlyOpt = False, viz: VizOpt = 0,
    cascade_estimator: EstimatorOpt = "top8", sampson_px: SampsonOpt = None, ratio: RatioOpt = None, label: LabelOpt = None,
    pairs: Annotated[Optional[Path], typer.Option("--pairs", help="Pair list (default ROOT/yfcc_test_pairs_with_gt.txt).")] = None,
    skip_missing: SkipMissingOpt = False, ransac_px: RansacOpt = None,
) -> None:
    """YFCC100M (or any SuperGlue-format pair list): pose AUC@5/10/20 and matching precision."""
    _benchmark_command("yfcc", {"pairs": pairs}, locals())


@app.command()
@friendly_errors
def table(
    run_dirs: Annotated[list[Path], typer.Argument(help="Run folders (each with config.yaml and summary.csv), one benchmark.")],
    out: Annotated[Path, typer.Option("--out", help="Table path; .csv and .md are written, plus a plot beside them.")],
    reference: Annotated[Optional[Path], typer.Option("--reference", help="Paper numbers (default results/paper/tableN.csv).")] = None,
    compare: CompareOpt = True,
) -> None:
    """Collect runs into the paper's table layout, with the paper's numbers and differences."""
    write_table(list(run_dirs), out, reference, compare, console)


@app.command()
@friendly_errors
def reproduce(
    config: Annotated[Path, typer.Argument(help="Experiment config, e.g. configs/table1_hpatches.yaml.")],
    root: RootOpt,
    out: OutOpt,
    backbone: Annotated[Optional[str], typer.Option("--backbone", help="Use this backbone for every deep method (labels say so).")] = None,
    limit: LimitOpt = None,
    device: DeviceOpt = "cpu",
    max_side: MaxSideOpt = None,
    scene_info: Annotated[Optional[list[Path]], typer.Option("--scene-info", help="MegaDepth: scene_info files instead of the config's.")] = None,
    pairs: Annotated[Optional[Path], typer.Option("--pairs", help="YFCC: pair list instead of the default.")] = None,
    sequences: Annotated[Optional[list[str]], typer.Option("--sequences", help="HPatches: sequences to keep.")] = None,
    skip_missing: SkipMissingOpt = False,
    compare: CompareOpt = True,
) -> None:
    """Run every method of a paper experiment (reusing cached matches) and write its table."""
    if not config.is_file():
        raise FileNotFoundError(f"{config}: experiment config not found (see configs/)")
    overrides = {"scene_info": scene_info, "pairs": pairs, "sequences": sequences}
    reproduce_experiment(config, root, out, backbone=backbone, limit=limit, device=device, dataset_overrides=overrides,
                         skip_missing=skip_missing, max_side=max_side, compare=compare, console=console)


def main() -> None:  # pragma: no cover - console entry point alias
    app()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(app())
