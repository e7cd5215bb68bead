"""Commands that bring data and matches in and out: download, datasets, import, export, synth."""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Annotated, Optional

import typer

from e3cm_bench.benchmarks import BENCHMARKS, get_benchmark
from e3cm_bench.cli.benchmarks import eval_options, keyword_parameters, option_parameter
from e3cm_bench.benchmarks.eval_options import EVAL_OPTIONS
from e3cm_bench.interchange.registry import formats, origin_help
from e3cm_bench.cli.common import (OnceEach, app, console, say, LabelOpt, ProtocolOpt, friendly_errors, typed_only,
                                   RootOpt, OutOpt, SeedOpt, OverwriteOpt, VizOpt, SkipBadOpt, PlotFormatOpt)

# The interchange formats' help, made from their registry (interchange/registry.py).
PixelOriginOpt = Annotated[Optional[str], typer.Option(
    "--pixel-origin", help=f"center (top-left pixel's centre at 0,0) or corner (at 0.5,0.5): overrides the format's "
                           "own "
                           f"({origin_help()}).")]
EXPORT_TO_HELP = ", ".join(f"{fmt.name} ({fmt.writes})" for fmt in formats().values())
MERGING = ", ".join(fmt.name for fmt in formats().values() if fmt.merges)


@app.command()
@friendly_errors
def download(
    name: Annotated[str, typer.Argument(help="hpatches, megadepth-1500, yfcc or scannet-1500.")],
    to: Annotated[Optional[Path], typer.Option("--to",
        help="Folder for the data (default: $E3CM_BENCH_DATA, else ./data).")] = None,
    origin: Annotated[Optional[str], typer.Option("--from",
                                                  help="A mirror URL or a file already downloaded, instead of the "
                                                       "source's URL.")] = None,
    sha256: Annotated[Optional[str], typer.Option("--sha256", help="The expected sha256 of the --from file.")] = None,
    check: Annotated[bool, typer.Option("--check",
                                        help="Only check what is in place (counts against a complete copy).")] = False,
) -> None:
    """Fetch a benchmark's data (progress, resume, sha256), unpack it safely, and check it."""
    from e3cm_bench.datasets.sources import data_dir, get_source
    from e3cm_bench.data.download import check as check_data
    from e3cm_bench.data.download import download as fetch_data

    source = get_source(name)
    to = to or data_dir()
    if not check:
        root = fetch_data(source, to, origin, sha256, console)
        console.print(f"{source.name}: in {root}", markup=False)
    console.print(check_data(source, to), markup=False)


@app.command()
@friendly_errors
def datasets(
    to: Annotated[Optional[Path], typer.Option("--root", "--to",
        help="The data folder that holds the benchmarks' folders (default: $E3CM_BENCH_DATA, else ./data); one "
             "benchmark's own folder (a benchmark command's --root) is read as the folder that holds it.")] = None,
) -> None:
    """Where each benchmark's data is looked for, and whether it is missing, incomplete or complete."""
    from e3cm_bench.datasets.sources import SOURCES, data_dir
    from e3cm_bench.data.download import status

    to = to or data_dir()
    # `datasets --root data/hpatches-sequences-release`, as a benchmark command takes it: the data
    # folder is the one that holds it (else every line would say 'missing' of a folder that is there)
    for source in SOURCES.values():
        if Path(to).resolve().as_posix().endswith("/" + source.folder):
            to = Path(to).resolve().parents[source.folder.count("/")]
            break
    say(f"data folder: {to} (benchmark commands use it when --root is not given)")
    for source in SOURCES.values():
        say(status(source, to))



def import_matches(
    benchmark: Annotated[str, typer.Argument(help=f"The benchmark: {', '.join(BENCHMARKS)}.")],
    out: OutOpt,
    root: RootOpt = None,
    pixel_origin: PixelOriginOpt = None,
    limit: Annotated[Optional[int], typer.Option("--limit",
                                                 help="Only the first N pairs (as a benchmark run's --limit).")] = None,
    label: LabelOpt = None,
    skip_bad: SkipBadOpt = False,
    overwrite: OverwriteOpt = False,
    viz: VizOpt = 0,
    seed: SeedOpt = 0,
    protocol: ProtocolOpt = None,  # None: the benchmark's default_protocol
    plot_format: PlotFormatOpt = "png",
    **options,  # one --FORMAT per interchange format (source_parameters), every benchmark's dataset options and
                # every evaluation option (eval_options.EVAL_OPTIONS)
) -> None:
    """Evaluate another tool's matches: a normal run folder (matches.h5, config.yaml with the sources' sha256, CSVs)."""
    from e3cm_bench.pipeline.imported import import_run
    from e3cm_bench.pipeline.resolve import resolve_request
    from e3cm_bench.data.download import find_root
    from e3cm_bench.storage import RunConfig

    known = formats()
    eval_given = {name: options.pop(name) for name in EVAL_OPTIONS if name in options}
    given_sources = {name: options.pop(name) for name in known if options.get(name) is not None}
    if len(given_sources) != 1:
        each = [f"--{fmt.name} {' '.join(fmt.reads)}" for fmt in known.values()]
        raise ValueError(f"give one source: {', '.join(each[:-1])} or {each[-1]} "
                         f"(given: {', '.join(f'--{name}' for name in given_sources) or 'none'})")
    bench = get_benchmark(benchmark)
    mine = {o.name for o in bench.command_options()}
    dataset_options = {k: v for k, v in options.items() if k not in known}
    foreign = sorted(OPTION_FLAGS[k] for k, v in dataset_options.items() if k not in mine and v not in (None, False,
            []))
    if foreign:
        raise ValueError(f"{', '.join(foreign)} do(es) not apply to {bench.name}")
    options = {k: _as_declared(bench, k, v) for k, v in dataset_options.items() if k in mine}
    # resolved as a benchmark command's options are; no matcher: the matches come from the files
    given = {"method": {"protocol": protocol, "seed": seed}, "evaluation": eval_given, "dataset": options,
             "run": {"out": out, "root": root, "limit": limit, "skip_bad": skip_bad, "overwrite": overwrite,
                     "viz": viz}}
    request = resolve_request(bench, typed_only(import_matches, given), locate=find_root)
    dataset = bench.load_dataset(request.root, skip_bad=skip_bad, **options)
    (name, paths), = given_sources.items()
    source = known[name].source(tuple(paths) if isinstance(paths, (tuple, list)) else (paths,), bench.name,
                                origin=pixel_origin)
    from e3cm_bench.drawing.formats import plots_as

    with plots_as(plot_format):
        request = request.but(dataset=dataset, dataset_load=RunConfig.dataset_load_of(request.root, skip_bad, options))
        import_run(request, source, label=label, console=console)


def _as_declared(bench, name: str, value):
    """`import` reads an option shared by several benchmarks as the first declares it (megadepth's
    --scene-info takes several files, sfm's one): the value as `bench` declares it."""
    kind = next(o.kind for o in bench.command_options() if o.name == name)
    if not isinstance(value, (list, tuple)) or kind in ("paths", "names"):
        return value
    if len(value) != 1:
        raise ValueError(f"{OPTION_FLAGS[name]}: {bench.name} takes one, given {len(value)}")
    return value[0]


def source_parameters() -> list[inspect.Parameter]:
    """`import`'s --FORMAT option of each registered format: a path, or a tuple of paths where the
    format reads more than one file (hloc: FEATURES.h5 MATCHES.h5)."""
    params = []
    for fmt in formats().values():
        kind = Path if len(fmt.reads) == 1 else tuple[(Path,) * len(fmt.reads)]
        option = typer.Option(f"--{fmt.name}", help=fmt.import_help, metavar=" ".join(fmt.reads))
        params.append(inspect.Parameter(fmt.name, inspect.Parameter.KEYWORD_ONLY, default=None,
                                        annotation=Annotated[Optional[kind], option]))
    return params


def all_dataset_parameters() -> list[inspect.Parameter]:
    """Every registered benchmark's dataset options, once each (for `import`, which takes the
    benchmark as an argument); the help names the benchmarks an option applies to."""
    seen: dict[str, tuple[object, list[str]]] = {}
    for bench in BENCHMARKS.values():
        for option in bench.command_options():
            seen.setdefault(option.name, (option, []))[1].append(bench.name)
    return [option_parameter(option, f"{', '.join(names)}: {option.help}") for option, names in seen.values()]


def _with_dataset_options(command):
    """`command` with each format's source option and every benchmark's dataset options added to its
    signature (typer reads it)."""
    signature = inspect.signature(command, eval_str=True)
    fixed = [p for p in signature.parameters.values() if p.kind is not inspect.Parameter.VAR_KEYWORD]
    fixed = [p.replace(kind=inspect.Parameter.KEYWORD_ONLY) if p.default is not inspect.Parameter.empty else p
             for p in fixed]
    # every evaluation option, as the benchmark commands have them: an import is scored as a run is
    params = fixed + source_parameters() + all_dataset_parameters() + keyword_parameters(eval_options())
    command.__signature__ = inspect.Signature(params)
    command.__annotations__ = {p.name: p.annotation for p in params}
    return command


OPTION_FLAGS = {o.name: o.flag for bench in BENCHMARKS.values() for o in bench.command_options()}
app.command("import", cls=OnceEach)(friendly_errors(_with_dataset_options(import_matches)))



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
    from e3cm_bench.apps.synth.stereo import write_stereo_sequence

    root = write_stereo_sequence(out, frames=frames, seed=seed)
    console.print(f"synth stereo: {frames} frames in {root} (image_0/, image_1/, calib.txt, poses.txt)", markup=False)



@app.command("export")
@friendly_errors
def export_matches(
    run: Annotated[Path, typer.Argument(help="A run folder (config.yaml, matches.h5).")],
    out: Annotated[Path, typer.Argument(help="Folder for the files.")],
    to: Annotated[str, typer.Option("--to", help=EXPORT_TO_HELP)],
    pixel_origin: PixelOriginOpt = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace the files already in OUT.")] = False,
    merge_px: Annotated[float, typer.Option("--merge-px",
                                            help=f"{MERGING}: write an image's keypoints within this many pixels of "
        "one another as one (exact repeats always are), for dense matchers.")] = 0.0,
) -> None:
    """Write a run's matches for another tool, in one of the formats of --to (docs: Matches in and out)."""
    from e3cm_bench.pipeline.export import export_run

    export_run(run, to, out, origin=pixel_origin, overwrite=overwrite, console=console, merge_px=merge_px)


if __name__ == "__main__":  # pragma: no cover
    app()

