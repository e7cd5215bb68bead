"""A method's options, declared once as data: name, kind, default, help, and what they concern.

Each `MethodOption` below is the one declaration of an option a user gives to choose a method
(a matcher and how it runs). Everything else is made from this table:

- the command line: cli/common.py turns an entry into the typer option of every command that
  takes it (`option_annotation`); the benchmark commands list theirs by name (cli/benchmarks.py);
- experiment configs: the keys a ``methods:`` entry and an experiment's top level accept, and
  the kind each value must be (`config_keys`, KINDS in ground/values.py; experiments.py);
- MethodSpec's validation: `check_method_values` on every option MethodSpec.create is given;
- the one path from options to a MethodSpec, method.build_method, starts from `with_defaults`
  (Benchmark.resolve_method is it for a benchmark; `match` and `calibrate`, which have none,
  call it without one).

Defaults merged with overrides: `with_defaults` fills what a caller left out from this table,
so that a command, a config and the Python API start from the same values.

Full resolution: wherever a user writes a longer side (``--max-side``, a config's ``max_side``,
a protocol's table, MethodSpec.create), full resolution is ``0`` (FULL_RESOLUTION), and an
absent value (None, the option not given) means "the default" (the protocol's or the
benchmark's; MethodSpec.create, which has no benchmark, takes None as full resolution too). The
old spellings keep working: None in a protocol table, ``null`` in a config (the default, as
before). A resolved MethodSpec records full resolution as ``max_side: null`` in config.yaml,
as every recorded identity has it (`resolved_side`).

This module imports nothing heavy: `e3cm-bench --help` reads it (tests/test_startup.py).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from e3cm_bench.backbones.names import BACKBONES, DEFAULT_BACKBONE, OFFLINE_BACKBONE
# the value kinds every section's options share (ground/values.py); named here for the method options
from e3cm_bench.ground.values import DATASET_KINDS, KINDS, Kind, KindOf, Range, check_value  # noqa: F401

FULL_RESOLUTION = 0  # a longer side of 0: the images as stored


def resolved_side(value, what: str = "max_side") -> int | None:
    """A side as a user wrote it -> the side a MethodSpec records: None (full resolution) for 0
    or None, else the positive number; anything else is a one-line ValueError."""
    if not (value is None or KINDS["whole"].test(value)):
        raise ValueError(
            f"{what} must be {FULL_RESOLUTION} (full resolution) or a positive whole number, got {value!r}"
        )
    return None if value in (None, FULL_RESOLUTION) else int(value)


# ---- the method options
# A seed is handed to numpy and OpenCV, which take 32 bits (cv2.setRNGSeed: a signed int); the
# evaluation's repeats and interval seeds count up from it (seed+1, ...), so some room is left.
SEEDS = Range(0, 2_000_000_000)
# A longer side in pixels (0: full resolution): a million is beyond any camera's image.
SIDES = Range(0, 1_000_000)


@dataclass(frozen=True)
class MethodOption(KindOf):
    """One option of a method.

    name: the keyword (MethodSpec.create, Benchmark.resolve_method) and the experiment-config key.
    flags: its spellings on the command line (the first is the name shown).
    kind: a key of KINDS. default: the value when none is given (None: "the default" the
    benchmark or the protocol decides, or none at all).
    concerns: which matchers it changes: "all", "deep" (matchers on a backbone), "shorthand"
    (the matchers whose registry entry lists it in `shorthands`), "weights" (matchers on a
    backbone or with a model of their own), "setting" (the matchers with a setting of its name:
    build_method hands it over among the settings, --set's value first, and a matcher without
    that setting refuses it, as it refuses an unknown --set).
    config: where an experiment config takes it: "method" (a ``methods:`` entry), "experiment"
    (the top level, every method's), "both" (the top level sets the methods' default), or ""
    (not in configs: the command line only, or as a matcher setting under ``settings:``).
    range: the values a number kind allows besides its kind (None: any of the kind).
    """

    name: str
    flags: tuple[str, ...]
    kind: str
    default: object
    help: str
    concerns: str = "all"
    config: str = "method"
    range: Range | None = None


_BACKBONE_HELP = (f"One of: {', '.join(BACKBONES)} ({DEFAULT_BACKBONE}: the paper's, downloads its ImageNet weights "
                  f"once; {OFFLINE_BACKBONE}: no download).")

METHOD_OPTIONS: dict[str, MethodOption] = {o.name: o for o in (
    MethodOption("matcher", ("--matcher",), "text", "e3cm",
                 "A matcher's name (e3cm-bench matchers lists them: built-ins and installed plugins) or "
                 "package.module:factory."),
    MethodOption("backbone", ("--backbone",), "text", DEFAULT_BACKBONE, _BACKBONE_HELP, "deep", "both"),
    MethodOption("weights", ("--weights",), "path", None,
                 "Local state-dict file for the backbone (instead of the ImageNet download).", "weights"),
    MethodOption("estimator", ("--estimator", "--cascade-estimator"), "text", None,
                 "e3cm: how the cascade estimates F per level: {estimators} (default top8 = the paper).", "shorthand"),
    MethodOption("sampson_px", ("--sampson-px",), "numbers", None,
                 "Sampson thresholds in pixels for levels 0,1,2,3, comma-separated.", "shorthand"),
    MethodOption("ratio", ("--ratio",), "numbers", None,
                 "Ratio-test thresholds for levels 0..4, comma-separated.", "shorthand"),
    MethodOption("max_side", ("--max-side",), "whole", None,
                 "Longer image side for matching (0 = full resolution).", "all", "both", SIDES),
    MethodOption("seed", ("--seed",), "whole", 0, "Seed of every RANSAC (set before each pair).", "all", "experiment",
                 SEEDS),
    MethodOption("label", ("--label",), "text", None,
                 "Method name in tables and plots (default: matcher[-backbone]).", "all", "method"),
    MethodOption("settings", ("--set",), "mapping", None,
                 "KEY=VALUE: a further matcher setting (repeatable), e.g. variant=corrected (dfm), ratio_at=own "
                 "(e3cm), cascade=false (e3cm-release), num_levels=4, channel_order=bgr."),
    MethodOption("precision", ("--precision",), "text", "fp32",
                 "Backbone precision: fp32 (exact, default), bf16 (CPUs with AVX-512 BF16/AMX, GPUs), fp16 (GPUs), "
                 "or auto: bf16 where the device computes it natively, else fp32 (fp16 on a GPU without bf16).",
                 "deep", ""),
    MethodOption("channel_order", ("--channel-order",), "text", "rgb",
                 "rgb (default) or bgr: the channel order fed to the network (the E3CM release's eval scripts feed "
                 "BGR).", "deep", ""),
    MethodOption("protocol", ("--protocol",), "text", None,
                 "Evaluation preset: {protocols}; default: wxbs on WxBS and EVD (their reference's), else default "
                 "(docs/benchmarks.md: Protocols).", "all", "experiment"),
)}


def config_keys(level: str) -> dict[str, str]:
    """The method options an experiment config takes at `level` ("method": a ``methods:`` entry,
    "experiment": the top level) -> their kind."""
    return {o.name: o.kind for o in METHOD_OPTIONS.values() if o.config in (level, "both")}


def with_defaults(given: Mapping) -> dict:
    """Every method option: `given`'s value where it has one (not None), else the table's default."""
    unknown = set(given) - set(METHOD_OPTIONS)
    if unknown:
        raise ValueError(f"unknown method option(s) {', '.join(sorted(unknown))}; "
                         f"a method takes {', '.join(METHOD_OPTIONS)}")
    return {name: given[name] if given.get(name) is not None else o.default for name, o in METHOD_OPTIONS.items()}


def check_method_values(values: Mapping) -> None:
    """MethodSpec's validation of the options it is given: each of its kind, one line naming the
    first that is not by its command-line flag (numbers may be tuples; a path a Path)."""
    for name, value in values.items():
        if name in METHOD_OPTIONS:
            METHOD_OPTIONS[name].check(value)
    label = values.get("label")
    if isinstance(label, str) and not label.isprintable():
        # a label is a table's row, a plot's legend and a file's name: one line of printable text
        raise ValueError(f"--label must be one line of printable text, got {label!r}")
    # The names, before anything is loaded (torch takes seconds): a backbone is one of the list
    # whatever the matcher (a matcher without one ignores it), a matcher one that exists.
    backbone = values.get("backbone")
    if isinstance(backbone, str) and backbone not in BACKBONES:
        from e3cm_bench.ground.suggest import did_you_mean

        raise ValueError(f"--backbone {backbone}: unknown backbone{did_you_mean(backbone, BACKBONES)}; "
                         f"choose one of: {', '.join(BACKBONES)}")
    if values.get("matcher") is not None:
        from e3cm_bench.matchers.registry import check_name

        check_name(values["matcher"])
