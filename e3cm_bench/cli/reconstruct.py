"""`e3cm-bench reconstruct IMAGES --out OUT`: one's own images, no ground truth, to a COLMAP model."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from e3cm_bench.cli.benchmarks import Scale, run_scaled
from e3cm_bench.cli.common import (app, console, eval_option, method_option, typed_only, warn, BackboneOpt,
                                   ChannelOrderOpt, DeviceOpt, LabelOpt,
                     FeatureCacheOpt, FeatureReuseOpt, MatcherOpt, OnMatcherErrorOpt, OutOpt, OverwriteOpt,
                     PairTimeoutOpt, PrecisionOpt,
                     SeedOpt, SetOpt, SkipBadOpt, WeightsOpt, friendly_errors, DevicesOpt, LauncherOpt, ShardOpt,
                     ShardsOpt, WorkersOpt)

ReconMaxSideOpt = method_option("max_side", help="Match at a longer side of at most N px (default 1200, as sfm; 0: "
                                                 "full resolution); keypoints are mapped back to the images' pixels.")


# reconstruct's own options (the others are every command's, cli/common.py)
WindowOpt = Annotated[Optional[int], typer.Option("--window", help="Pairs: each image with the next K in name order "
                                                                   "(default: every pair).")]
PairsOpt = Annotated[Optional[Path], typer.Option("--pairs", help="Pairs: a file of 'name0 name1' lines, names "
                                                                  "relative to IMAGES.")]
MaxPairsOpt = Annotated[Optional[int], typer.Option("--max-pairs", help="The most pairs a run builds (default 20000): "
                                                    "more is refused before any is made.")]
AllowDisconnectedOpt = Annotated[bool, typer.Option("--allow-disconnected", help="Accept a pair graph in several "
                                                    "components (each gives models of its own).")]
# the reconstruction's protocol: evaluation options, declared once (benchmarks/eval_options.py)
MapperOpt, MapperSeedsOpt, MergePxOpt = (eval_option(name) for name in ("mapper", "mapper_seeds", "merge_px"))
CameraModelOpt = Annotated[str, typer.Option("--camera-model", help="SIMPLE_RADIAL (COLMAP's default) or PINHOLE; "
                                                                    "intrinsics unknown, refined by the mapper.")]
CameraPerImageOpt = Annotated[bool, typer.Option("--camera-per-image", help="One camera per image (default: images "
                                                                            "of one size share one).")]


@app.command()
@friendly_errors
def reconstruct(
    images: Annotated[Path, typer.Argument(help="The folder of images (sub-folders included), named in the model by "
                                                "their paths under it.")],
    out: OutOpt,
    matcher: MatcherOpt = "e3cm",
    window: WindowOpt = None,
    pairs: PairsOpt = None,
    merge_px: MergePxOpt = None,
    max_pairs: MaxPairsOpt = None,
    allow_disconnected: AllowDisconnectedOpt = False,
    mapper: MapperOpt = None,
    mapper_seeds: MapperSeedsOpt = None,
    camera_model: CameraModelOpt = "SIMPLE_RADIAL",
    camera_per_image: CameraPerImageOpt = False,
    backbone: BackboneOpt = None,
    weights: WeightsOpt = None,
    max_side: ReconMaxSideOpt = None,
    settings: SetOpt = None,
    label: LabelOpt = None,
    precision: PrecisionOpt = "fp32",
    channel_order: ChannelOrderOpt = "rgb",
    seed: SeedOpt = 0,
    device: DeviceOpt = "cpu",
    overwrite: OverwriteOpt = False,
    feature_cache_mb: FeatureCacheOpt = None,
    feature_reuse: FeatureReuseOpt = True,
    skip_bad: SkipBadOpt = False,
    on_matcher_error: OnMatcherErrorOpt = "stop",
    pair_timeout: PairTimeoutOpt = None,
    shard: ShardOpt = None,
    workers: WorkersOpt = 0,
    devices: DevicesOpt = None,
    launcher: LauncherOpt = "local",
    shards: ShardsOpt = 0,
) -> None:
    """Your own images, no ground truth: pairs -> matches (cached in OUT, resumable) -> COLMAP's verification and
    pycolmap's mapper -> the model in OUT/sparse/N (COLMAP binary and text)."""
    from e3cm_bench.pipeline.resolve import resolve_request
    from e3cm_bench.sfm.own_images import RECONSTRUCT  # a benchmark that is no command (benchmarks.UNLISTED)

    scale = Scale(shard, workers, devices, launcher, shards)
    scale.check(device=device)  # the flags first: building the method may download weights
    given = {"method": dict(matcher=matcher, backbone=backbone, weights=weights, settings=settings, label=label,
                            precision=precision, channel_order=channel_order, seed=seed, max_side=max_side),
             "evaluation": dict(mapper=mapper, mapper_seeds=mapper_seeds, merge_px=merge_px),
             "dataset": dict(window=window, pairs=pairs, camera_model=camera_model, camera_per_image=camera_per_image,
                             max_pairs=max_pairs, allow_disconnected=allow_disconnected),
             "run": dict(out=out, root=images, skip_bad=skip_bad, overwrite=overwrite, device=device, shard=shard),
             "match": dict(feature_cache_mb=feature_cache_mb, on_matcher_error=on_matcher_error,
                           pair_timeout=pair_timeout, feature_reuse=feature_reuse)}
    request = resolve_request(RECONSTRUCT, typed_only(reconstruct, given), warn=warn)
    run_scaled(scale, request)
    _say_model(Path(out), scale)


def _say_model(out: Path, scale) -> None:
    """Where the model is and what it holds (OUT's summary); a shard's run says when it is made."""
    import pandas as pd

    from e3cm_bench.pipeline.shards import all_shards_complete
    from e3cm_bench.sfm.own_images import fragments
    from e3cm_bench.sfm.uncalibrated import SPARSE
    from e3cm_bench.storage.folder import RunFolder

    # a sharded run's model is the merge's: made by the last shard to finish, or by merge
    if (scale.shard or scale.launcher == "slurm") and not all_shards_complete(out):
        console.print(f"the model of every image is made when the last shard finishes (or: e3cm-bench merge {out})",
                      markup=False, soft_wrap=True)
        return
    row = pd.read_csv(RunFolder(out).summary_path).iloc[0]
    if int(row["n_models"]) == 0 or not (out / SPARSE / "0").is_dir():  # name no folder that is not there
        console.print(f"no model: 0 of {int(row['n_images'])} images registered; the verified pairs are in "
                      f"{out / 'database.db'}, the matches per pair in {RunFolder(out).per_pair_path}",
                      markup=False, soft_wrap=True)
        return
    points = row.get("largest_model_points")
    console.print(f"{int(row['registered_images'])} of {int(row['n_images'])} images registered in "
                  f"{int(row['n_models'])} model(s); the largest, {out / SPARSE / '0'}, holds "
                  f"{int(row['largest_model_images'])} images"
                  + (f" and {int(points)} points" if points is not None and pd.notna(points) else "")
                  + " (COLMAP binary and text: colmap gui --import_path, pycolmap.Reconstruction)",
                  markup=False, soft_wrap=True)
    note = fragments(row)
    if note:
        warn(note)


MatchersOpt = Annotated[str, typer.Option("--matchers", help="The matchers to rank, comma-separated: names (e3cm-bench "
                                                             "matchers lists them) or package.module:factory.")]


@app.command()
@friendly_errors
def rank(
    images: Annotated[Path, typer.Argument(
        help="The folder of images (sub-folders included), as reconstruct reads it.")],
    out: OutOpt,
    matchers: MatchersOpt,
    window: WindowOpt = None,
    pairs: PairsOpt = None,
    max_pairs: MaxPairsOpt = None,
    allow_disconnected: AllowDisconnectedOpt = False,
    mapper: MapperOpt = None,
    mapper_seeds: MapperSeedsOpt = None,
    camera_model: CameraModelOpt = "SIMPLE_RADIAL",
    camera_per_image: CameraPerImageOpt = False,
    backbone: BackboneOpt = None,
    max_side: ReconMaxSideOpt = None,
    precision: PrecisionOpt = "fp32",
    seed: SeedOpt = 0,
    device: DeviceOpt = "cpu",
) -> None:
    """Which matcher for your images, at what cost: each matcher reconstructs the folder (as reconstruct does, into
    OUT/runs/NAME), then they are ranked without ground truth by how well each one's poses agree with the others'
    reconstructions -> OUT/verdict.csv and OUT/index.html (docs/own-images.md)."""
    from e3cm_bench.apps.rank import RankRequest, print_verdict, rank_folder

    request = RankRequest(images, out, tuple(m.strip() for m in matchers.split(",") if m.strip()),
                          method=dict(backbone=backbone, max_side=max_side, precision=precision, seed=seed),
                          dataset_options=dict(window=window, pairs=pairs, camera_model=camera_model,
                                               camera_per_image=camera_per_image, max_pairs=max_pairs,
                                               allow_disconnected=allow_disconnected),
                          evaluation=dict(mapper=mapper, mapper_seeds=mapper_seeds),
                          seed=seed, device=device)
    print_verdict(rank_folder(request, console), Path(out), console)
