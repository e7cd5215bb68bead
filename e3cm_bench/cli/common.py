"""What every command shares: the application, its consoles, the options used by several
commands, the settings parser, and the one-line error wrapper.

Startup: every invocation, `--help` and a mistyped command included, imports this package
before typer reads a word of the command line, so the modules of the command line import at
their top only what their help needs (typer, rich, the benchmark registry and torch-free name
lists: backbone_names, matching's estimators, the protocols); torch, scipy and the run
machinery are imported inside the command that uses them. tests/test_startup.py holds this;
scripts/maintain/startup_time.py measures it.
"""

from __future__ import annotations

import functools
import os
import shutil
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console
from rich.markup import escape
from typer.core import TyperCommand

from e3cm_bench import __version__
from e3cm_bench.benchmarks import BENCHMARKS
from e3cm_bench.method.protocols import PROTOCOLS
from e3cm_bench.matching import ESTIMATORS
from e3cm_bench.method.options import METHOD_OPTIONS
from e3cm_bench.drawing.formats import LogConsole
from e3cm_bench.benchmarks.eval_options import EVAL_OPTIONS
from e3cm_bench.method.spec import method_values, parse_settings  # noqa: F401 - the commands' names for them


def app_help() -> str:
    """The top-level help, its benchmarks read from the registry: a list written by hand once
    left out sfm, and would miss the next benchmark too."""
    return (f"Training-free deep feature matching (E3CM, DFM, SIFT+NN) and its benchmarks, one command each: "
            f"{', '.join(BENCHMARKS)}.")


app = typer.Typer(add_completion=False, no_args_is_help=True, help=app_help())
class _Console(LogConsole, Console):
    """The commands' consoles: messages unwrapped in a pipe (drawing/formats.LogConsole)."""


console = _Console()
err_console = _Console(stderr=True)


def _print_version(given: bool) -> None:
    if given:
        console.print(f"e3cm-bench {__version__}", markup=False, highlight=False)
        raise typer.Exit()


@app.callback()
def main(
    version: Annotated[bool, typer.Option("--version", is_eager=True, callback=_print_version,
                                          help="Print the version and exit.")] = False,
) -> None:
    """The application's options (its help is app_help's)."""


def method_option(name: str, help: str | None = None, flags: tuple[str, ...] | None = None):
    """The typer option of a method option, made from its one declaration (options.METHOD_OPTIONS):
    its flags, type and help (`help`, `flags`: a command's own words, where they differ)."""
    option = METHOD_OPTIONS[name]
    text = (help or option.help).format(estimators=", ".join(ESTIMATORS), protocols=", ".join(PROTOCOLS))
    return Annotated[option.cli_type, typer.Option(*(flags or option.flags), help=text)]


def eval_option(name: str):
    """The typer option of an evaluation option, made from its one declaration (eval_options.EVAL_OPTIONS)."""
    option = EVAL_OPTIONS[name]
    return Annotated[option.cli_type, typer.Option(option.flag, help=option.help, show_default=option.show_default
                                                   if option.show_default is not None else True)]


# Options shared by `match`, `reconstruct` and `import` (the benchmark commands take every method
# and evaluation option from its table: cli/benchmarks.py common_before, common_after).
MatcherOpt = method_option("matcher")
BackboneOpt = method_option("backbone")
WeightsOpt = method_option("weights")
EstimatorOpt = method_option("estimator")
SampsonOpt = method_option("sampson_px")
RatioOpt = method_option("ratio")
LabelOpt = method_option("label")
SetOpt = method_option("settings")
PrecisionOpt = method_option("precision")
ChannelOrderOpt = method_option("channel_order")
ProtocolOpt = method_option("protocol")
MaxSideOpt = method_option("max_side")
SeedOpt = method_option("seed")
DeviceOpt = Annotated[str, typer.Option("--device", help="cpu, cuda or mps.")]
BackboneBatchOpt = Annotated[
    Optional[int],
    typer.Option(
        "--backbone-batch",
        show_default="8 on a GPU, 1 on a CPU",
        help="Images per backbone pass: when a pair needs a pass, the coming pairs' images of the same size that the "
             "feature cache lacks go through the network with it (for GPUs; needs the cache).",
    ),
]
FeatureCacheOpt = Annotated[
    Optional[float],
    typer.Option(
        "--feature-cache-mb",
        show_default="half the available memory, at most 16 GiB",
        help="Memory (MiB) for the feature maps of images that have pairs left (what does not fit goes to the run "
             "folder, up to half the free disk, at most 64 GiB); 0 = no reuse. Never changes a result.",
    ),
]
FeatureReuseOpt = Annotated[
    bool,
    typer.Option(
        "--feature-reuse/--no-feature-reuse",
        help="Extract a two-stage matcher's features once per image and match every pair from them (in the feature "
             "cache); --no-feature-reuse: pair by pair, each pair extracting both its images. Never changes a result.",
    ),
]


def typed_only(command, given: dict) -> dict:
    """A command's options by section (pipeline/resolve.py), those at the command's own default left
    out: what the user typed, as a run's record keeps it (`given`); the matcher always, as the one
    that makes the run a method's."""
    import inspect

    return leave_defaults(given, {name: p.default for name, p in inspect.signature(command).parameters.items()})


def leave_defaults(given: dict, defaults: dict) -> dict:
    """`given` by section without the options whose value is their default (the matcher kept)."""
    return {section: {k: v for k, v in values.items() if k == "matcher" or k not in defaults or v != defaults[k]}
            for section, values in given.items()}


def say(line: str, hang: int = 4) -> None:
    """A line of plain text on stdout within the terminal's width (80 columns in a pipe or a log:
    drawing/formats.text_width), words kept whole (a path too), its continuation lines indented
    `hang` spaces more than it (a listing's entries stay apart)."""
    from e3cm_bench.drawing.formats import print_wrapped

    print_wrapped(console, line, hang)


def warn(message: str) -> None:
    """A warning on stderr (method.build_method's `warn`: a precision that will be emulated)."""
    tell(message, "warning", "yellow")


def tell(message: str, label: str = "error", style: str = "bold red") -> None:
    """`label: message` on stderr. On a terminal it is wrapped to the terminal's width, words kept
    whole, its continuation lines indented under the text after the label; anywhere else (a pipe,
    a log, CI, the tests) it stays one physical line, however long, so that grep or a script
    reading the last line of stderr gets all of it (docs/cli.md, "Output")."""
    import textwrap

    try:
        terminal = err_console.file.isatty()
    except (AttributeError, ValueError, OSError):
        terminal = False
    head = f"{label}: "
    if not terminal:
        lines = [head + message]
    else:  # rich's width: the terminal's, or COLUMNS where set
        lines = textwrap.wrap(head + message, max(err_console.width, 2 * len(head)), subsequent_indent=" " * len(head),
                              break_long_words=False, break_on_hyphens=False) or [head]
    text = "\n".join([f"[{style}]{label}:[/] {escape(lines[0][len(head):])}", *map(escape, lines[1:])])
    err_console.print(text, highlight=False, soft_wrap=True)  # escape: a path may hold [/]


# The commands that write run folders (with every benchmark's own): only their rerun resumes at
# the first pair not written.
RESUMING_COMMANDS = frozenset({"reproduce", "import_matches", "calibrate", "demo", "reconstruct"})


def os_error_line(exc: OSError, resumes: bool = False) -> str:
    """One line for an OSError: the file, the problem, and for a full disk what to do (`resumes`:
    the command is a benchmark's or one of RESUMING_COMMANDS)."""
    import errno

    where = str(exc.filename or "")  # pathlib's errors name a Path
    text = exc.strerror or str(exc)
    disk_full = getattr(sys.modules.get("e3cm_bench.storage.cache"), "DiskFullError", ())  # raised only once imported
    if isinstance(exc, disk_full) or exc.errno != errno.ENOSPC:
        return f"{where}: {text}" if where and where not in text else text
    # The free space of the filesystem that filled: the nearest existing folder of the file
    # named. A failed write() names no file: then nothing is quoted, not some other disk's space.
    existing = next((p for p in (Path(where), *Path(where).parents) if p.exists()), None) if where else None
    free = ""
    try:
        free = f" ({shutil.disk_usage(existing).free / 2**20:.1f} MiB free there)" if existing is not None else ""
    except OSError:
        pass
    return (f"{where or 'the output folder'}: no space left on device{free}; free some space and rerun the same "
            "command" + (": every pair already written resumes" if resumes else ""))


def _bad_input_errors() -> tuple[type[BaseException], ...]:
    """The exceptions that mean bad input (one line, exit 2): ValueError, FileNotFoundError,
    KeyError, and the package's own DatasetError and BackboneError. Those two are looked up
    only in modules already imported (an exception of a module never imported cannot have been
    raised), so that the wrapper needs neither torch nor OpenCV to exist."""
    found: list[type[BaseException]] = [ValueError, FileNotFoundError, KeyError]
    for module, name in (
        ("e3cm_bench.datasets.base", "DatasetError"),
        ("e3cm_bench.backbones.pyramid", "BackboneError"),
    ):
        cls = getattr(sys.modules.get(module), name, None)
        if cls is not None:
            found.append(cls)
    return tuple(found)


def _out_of_address_space(exc: ImportError) -> bool:
    """The dynamic loader's words for a shared object it had no room to map."""
    text = str(exc)
    return "failed to map segment" in text or "cannot allocate memory" in text.lower()


def friendly_errors(command):
    """Bad input ends in one line on stderr and a non-zero exit, never a traceback.

    E3CM_BENCH_DEBUG=1 lets the exception through with its traceback (for developers).
    """

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            return command(*args, **kwargs)
        except _bad_input_errors() as exc:  # evaluated when an exception comes, after the command's imports
            if os.environ.get("E3CM_BENCH_DEBUG"):
                raise
            message = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            tell(message)
            raise typer.Exit(2) from None
        except MemoryError as exc:
            if os.environ.get("E3CM_BENCH_DEBUG"):
                raise
            detail = str(exc).strip().splitlines()[0] if str(exc).strip() else "not enough memory"
            tell(f"out of memory: {detail}")
            raise typer.Exit(2) from None
        except ImportError as exc:
            # A library that cannot be mapped into memory (the commands import torch only when they
            # match, so under `ulimit -v` this is where the limit is met first) is the memory case
            # above, not a bug; a broken library is one line (library_errors.py); an
            # ImportError in e3cm-bench's own code keeps its traceback.
            if os.environ.get("E3CM_BENCH_DEBUG"):
                raise
            if not _out_of_address_space(exc):
                from e3cm_bench.ground.library_errors import broken_library_line

                line = broken_library_line(exc)
                if line is None:
                    raise
                tell(line.removeprefix("error: "))
                raise typer.Exit(2) from None
            tell(f"out of memory: a library could not be loaded ({exc}); raise the address-space or memory limit "
                 "(ulimit -v) and rerun: matches already written are kept")
            raise typer.Exit(2) from None
        except OSError as exc:  # a full disk, a folder that cannot be written: what and where, in one line
            if os.environ.get("E3CM_BENCH_DEBUG"):
                raise
            name = command.__name__
            line = os_error_line(exc, resumes=name in RESUMING_COMMANDS or name.replace("_", "-") in BENCHMARKS)
            tell(line)
            raise typer.Exit(2) from None
        except KeyboardInterrupt:
            err_console.print(
                "[yellow]interrupted[/]: matches written so far are kept; rerun the same command to resume"
            )
            raise typer.Exit(130) from None

    return wrapper



class OnceEach(TyperCommand):
    """A command whose options of one value may each be given once: click keeps the last of a
    repeated one without a word (`sfm --graph A --graph B` matched B's pairs only). Options
    that collect (--set, --scene-info of megadepth) and switches may repeat."""

    def parse_args(self, ctx, args: list[str]) -> list[str]:
        given: dict[str, int] = {}
        for arg in args:
            if arg == "--":
                break
            if arg.startswith("--"):
                flag = arg.split("=", 1)[0]
                given[flag] = given.get(flag, 0) + 1
        for param in self.params:
            if getattr(param, "param_type_name", "") != "option" or param.multiple or param.is_flag or param.nargs != 1:
                continue
            times = sum(given.get(flag, 0) for flag in param.opts)
            if times > 1:
                tell(f"{param.opts[0]} is given {times} times; it takes one value, give it once")
                ctx.exit(2)
        return super().parse_args(ctx, args)


ShardOpt = Annotated[
    Optional[str],
    typer.Option(
        "--shard",
        help="K/N: run only the K-th of N slices of the pairs, into OUT/shards/K-of-N/ (the last shard merges).",
    ),
]
WorkersOpt = Annotated[
    int,
    typer.Option(
        "--workers", help="Run N shards at once in N local processes, CPU threads divided among them, then merge."
    ),
]
DevicesOpt = Annotated[
    Optional[str], typer.Option("--devices", help="cuda:0,cuda:1,...: one shard and process per device, then merge.")
]
LauncherOpt = Annotated[
    str,
    typer.Option(
        "--launcher", help="slurm: submit --shards N as a SLURM array (submitit; runs locally where SLURM is absent)."
    ),
]
ShardsOpt = Annotated[int, typer.Option("--shards", help="Number of shards for --launcher slurm.")]
RootOpt = Annotated[
    Optional[Path],
    typer.Option(
        "--root",
        help="Dataset root folder (default: the downloaded data under $E3CM_BENCH_DATA, else ./data; e3cm-bench "
             "datasets).",
    ),
]
OutOpt = Annotated[Path, typer.Option("--out", help="Run folder (config.yaml, matches.h5, CSVs, plots).")]
LimitOpt = Annotated[Optional[int], typer.Option("--limit", help="Only the first N pairs.")]
OverwriteOpt = Annotated[bool, typer.Option("--overwrite", help="Discard matches already in --out.")]
EvalOnlyOpt = Annotated[
    bool, typer.Option("--eval-only", help="Recompute the metrics from matches.h5 without matching.")
]
VizOpt = Annotated[
    int, typer.Option("--viz", help="Draw the first N pairs (green: correct by ground truth, red: not).")
]
SkipBadOpt = Annotated[
    bool,
    typer.Option(
        "--skip-bad",
        "--skip-missing",
        help="Skip the pairs with bad input (images missing or cut short, unusable ground truth), list them in "
             "skipped.csv and count them; --skip-missing is the old name.",
    ),
]
CompareOpt = Annotated[
    bool,
    typer.Option(
        "--compare/--no-compare",
        help="Difference columns (measured - paper); off for data other than the paper's benchmark.",
    ),
]
OnMatcherErrorOpt = Annotated[
    str,
    typer.Option(
        "--on-matcher-error",
        help="stop (default): a matcher that raises on a pair ends the run (the pairs before it are kept); fail-pair: "
             "that pair counts as a failure (no matches), its message goes to failures.csv, and the run goes on.",
    ),
]
PairTimeoutOpt = Annotated[
    Optional[float],
    typer.Option(
        "--pair-timeout",
        help="Seconds a matcher may take on one pair; past them the matcher is stopped with every process it started "
             "and the pair fails as --on-matcher-error says (POSIX; default: no limit).",
    ),
]
# Help texts are Rich markup: a literal "[word]" needs its backslash, else Rich takes it for a
# style and drops it (tests/test_startup.py reads every help as Rich renders it).
PlotFormatOpt = Annotated[
    str, typer.Option("--format", help="File format of the plots written: png, pdf or svg (vector, for a paper).")
]
