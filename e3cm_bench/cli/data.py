"""Commands that bring data and matches in and out: download, datasets, import, export, synth."""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Annotated, Optional

import typer

from ..benchmarks import BENCHMARKS, get_benchmark
from .benchmarks import option_parameter
from .common import app, console, LabelOpt, ProtocolOpt, friendly_errors, RootOpt, OutOpt, SeedOpt, OverwriteOpt, VizOpt, SkipBadOpt, RansacOpt, PoseEstimatorOpt


@app.command()
@friendly_errors
def download(
    name: Annotated[str, typer.Argument(help="hpatches, megadepth-1500, yfcc or scannet-1500.")],
    to: Annotated[Optional[Path], typer.Option("--to", help="Folder for the data (default: $E3CM_BENCH_DATA, else ./data).")] = None,
    origin: Annotated[Optional[str], typer.Option("--from", help="A mirror URL or a file already downloaded, instead of the source's URL.")] = None,
    sha256: Annotated[Optional[str], typer.Option("--sha256", help="The expected sha256 of the --from file.")] = None,
    check: Annotated[bool, typer.Option("--check", help="Only check what is in place (counts against a complete copy).")] = False,
) -> None:
    """Fetch a benchmark's data (progress, resume, sha256), unpack it safely, and check it."""
    from ..datasets.sources import data_dir, get_source
    from ..download import check as check_data
    from ..download import download as fetch_data

    source = get_source(name)
    to = to or data_dir()
    if not check:
        root = fetch_data(source, to, origin, sha256, console)
        console.print(f"{source.name}: in {root}", markup=False)
    console.print(check_data(source, to), markup=False)


@app.command()
@friendly_errors
def datasets(
    to: Annotated[Optional[Path], typer.Option("--to", help="The data folder (default: $E3CM_BENCH_DATA, else ./data).")] = None,
) -> None:
    """Where each benchmark's data is looked for, and whether it is missing, incomplete or complete."""
    from ..datasets.sources import SOURCES, data_dir
    from ..download import status

    to = to or data_dir()
    console.print(f"data folder: {to} (benchmark commands use it when --root is not given)", markup=False)
    for source in SOURCES.values():
        console.print(status(source, to), markup=False, highlight=False, soft_wrap=True)



def import_matches(
    benchmark: Annotated[str, typer.Argument(help=f"The benchmark: {', '.join(BENCHMARKS)}.")],
    out: OutOpt,
    root: RootOpt = None,
    hloc: Annotated[Optional[tuple[Path, Path]], typer.Option("--hloc", help="FEATURES.h5 MATCHES.h5 written by hloc (or in its layout).")] = None,
    npz: Annotated[Optional[Path], typer.Option("--npz", help="Folder of <pair name>.npz (keypoints0, keypoints1, optional scores).")] = None,
    colmap: Annotated[Optional[Path], typer.Option("--colmap", help="A COLMAP database.db (images named by their path under the root; needs pycolmap).")] = None,
    gluefactory: Annotated[Optional[Path], typer.Option("--gluefactory", help="glue-factory's predictions.h5 (its evaluation cache).")] = None,
    pixel_origin: Annotated[Optional[str], typer.Option("--pixel-origin", help="center (top-left pixel's centre at 0,0) or corner (at 0.5,0.5): overrides the format's own (hloc, npz: center; colmap, gluefactory: corner).")] = None,
    limit: Annotated[Optional[int], typer.Option("--limit", help="Only the first N pairs (as a benchmark run's --limit).")] = None,
    label: LabelOpt = None,
    skip_bad: SkipBadOpt = False,
    overwrite: OverwriteOpt = False,
    viz: VizOpt = 0,
    seed: SeedOpt = 0,
    ransac_px: RansacOpt = None,
    pose_estimator: PoseEstimatorOpt = None,
    protocol: ProtocolOpt = None,  # None: the benchmark's default_protocol
    **dataset_options,
) -> None:
    """Evaluate matches made by another tool: writes a normal run folder (matches.h5, config.yaml with the sources' sha256, CSVs, plots)."""
    from ..imported import ColmapSource, GluefactorySource, HlocSource, NpzSource, import_run
    from ..download import find_root
    from ..run import RunConfig

    given = [name for name, value in (("--hloc", hloc), ("--npz", npz), ("--colmap", colmap),
                                      ("--gluefactory", gluefactory)) if value is not None]
    if len(given) != 1:
        raise ValueError("give one source: --hloc FEATURES.h5 MATCHES.h5, --npz DIR, --colmap DATABASE.db or "
                         f"--gluefactory PREDICTIONS.h5 (given: {', '.join(given) or 'none'})")
    bench = get_benchmark(benchmark)
    root = find_root(bench.name, root)
    mine = {o.name for o in bench.command_options()}
    foreign = sorted(OPTION_FLAGS[k] for k, v in dataset_options.items() if k not in mine and v not in (None, False, []))
    if foreign:
        raise ValueError(f"{', '.join(foreign)} do(es) not apply to {bench.name}")
    options = {k: v for k, v in dataset_options.items() if k in mine}
    dataset = bench.load_dataset(root, skip_bad=skip_bad, **options)
    ev = bench.resolve_eval(protocol, seed, ransac_px, pose_estimator)
    if hloc is not None:
        source = HlocSource(*hloc, origin=pixel_origin)
    elif npz is not None:
        source = NpzSource(npz, origin=pixel_origin)
    elif colmap is not None:
        source = ColmapSource(colmap, origin=pixel_origin)
    else:
        source = GluefactorySource(gluefactory, bench.name, origin=pixel_origin)
    import_run(bench, dataset, root, out, source, ev=ev, label=label, skip_bad=skip_bad, overwrite=overwrite, viz=viz,
               console=console, limit=limit, dataset_load=RunConfig.dataset_load_of(root, skip_bad, options))


def all_dataset_parameters() -> list[inspect.Parameter]:
    """Every registered benchmark's dataset options, once each (for `import`, which takes the
    benchmark as an argument); the help names the benchmarks an option applies to."""
    seen: dict[str, tuple[object, list[str]]] = {}
    for bench in BENCHMARKS.values():
        for option in bench.command_options():
            seen.setdefault(option.name, (option, []))[1].append(bench.name)
    return [option_parameter(option, f"{', '.join(names)}: {option.help}") for option, names in seen.values()]


def _with_dataset_options(command):
    """`command` with every benchmark's dataset options added to its signature (typer reads it)."""
    signature = inspect.signature(command, eval_str=True)
    fixed = [p for p in signature.parameters.values() if p.kind is not inspect.Parameter.VAR_KEYWORD]
    fixed = [p.replace(kind=inspect.Parameter.KEYWORD_ONLY) if p.default is not inspect.Parameter.empty else p
             for p in fixed]
    params = fixed + all_dataset_parameters()
    command.__signature__ = inspect.Signature(params)
    command.__annotations__ = {p.name: p.annotation for p in params}
    return command


OPTION_FLAGS = {o.name: o.flag for bench in BENCHMARKS.values() for o in bench.command_options()}
app.command("import")(friendly_errors(_with_dataset_options(import_matches)))



synth_app = typer.Typer(no_args_is_help=True, help="Write synthetic data with exact ground truth.")
app.add_typer(synth_app, name="synth")


@synth_app.command("stereo")
@friendly_errors
def synth_stereo(
    out: Annotated[Path, typer.Option("--out", help="Sequence folder (KITTI odometry layout).")],
    frames: Annotated[int, typer.Option("--frames", help="Number of stereo frames.")] = 20,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the scene, the rig's drift and its path.")] = 0,
) -> None:
    """A stereo rig with a drifted extrinsic (about 1 degree each angle) moving through the demo's room scene."""
    from ..synth.stereo import write_stereo_sequence

    root = write_stereo_sequence(out, frames=frames, seed=seed)
    console.print(f"synth stereo: {frames} frames in {root} (image_0/, image_1/, calib.txt, poses.txt)")



@app.command("export")
@friendly_errors
def export_matches(
    run: Annotated[Path, typer.Argument(help="A run folder (config.yaml, matches.h5).")],
    out: Annotated[Path, typer.Argument(help="Folder for the files.")],
    to: Annotated[str, typer.Option("--to", help="colmap (database.db), hloc (features.h5, matches.h5), gluefactory (predictions.h5) or npz (the folder import --npz reads).")],
    pixel_origin: Annotated[Optional[str], typer.Option("--pixel-origin", help="center or corner: overrides the format's own convention (hloc, npz: center; colmap, gluefactory: corner).")] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace the files already in OUT.")] = False,
    merge_px: Annotated[float, typer.Option("--merge-px", help="colmap, hloc: write an image's keypoints within this many pixels of one another as one (exact repeats always are), for dense matchers.")] = 0.0,
) -> None:
    """Write a run's matches for another tool: COLMAP, hloc, glue-factory or npz (docs: Matches in and out)."""
    from ..interchange import export_run

    export_run(run, to, out, origin=pixel_origin, overwrite=overwrite, console=console, merge_px=merge_px)


if __name__ == "__main__":  # pragma: no cover
    app()

