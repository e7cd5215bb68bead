"""The matcher listing and the stereo calibration."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from e3cm_bench.backbones.names import DEFAULT_BACKBONE
from e3cm_bench.cli.common import (
    app,
    console,
    say,
    method_values,
    method_option,
    BackboneOpt,
    WeightsOpt,
    DeviceOpt,
    friendly_errors,
    OutOpt,
    SeedOpt,
    OverwriteOpt,
    PlotFormatOpt,
)


# calibrate's own words for two method options (declared in options.METHOD_OPTIONS)
CalibrateMaxSideOpt = method_option("max_side", help="Longer image side for matching (default: full resolution).")
CalibrateSetOpt = method_option(
    "settings",
    help="KEY=VALUE: a further setting of the deep matchers (repeatable), e.g. refine=ncc; the label shows it.",
)


@app.command()
@friendly_errors
def calibrate(
    root: Annotated[
        Path,
        typer.Option(
            "--root",
            help="Stereo sequence: KITTI odometry (image_0/, image_1/, calib.txt) or raw (image_00/data, "
                 "image_01/data, calib_cam_to_cam.txt) layout.",
        ),
    ],
    out: OutOpt,
    matcher: Annotated[
        list[str],
        typer.Option(
            "--matcher", help="Matcher(s) to compare (repeatable), as for the benchmarks (e3cm-bench matchers)."
        ),
    ] = ["e3cm"],  # noqa: B006
    backbone: BackboneOpt = DEFAULT_BACKBONE,
    weights: WeightsOpt = None,
    frames: Annotated[
        list[int], typer.Option("--frames", help="Window sizes in frames (repeatable; default 1 3 5 10).")
    ] = [1, 3, 5, 10],  # noqa: B006
    max_side: CalibrateMaxSideOpt = None,
    seed: SeedOpt = 0,
    device: DeviceOpt = "cpu",
    unrectified: Annotated[
        bool,
        typer.Option(
            "--unrectified",
            help="KITTI raw: the unrectified images (K_0x, R_01, T_01) instead of the rectified ones (P_rect_0x).",
        ),
    ] = False,
    overwrite: OverwriteOpt = False,
    settings: CalibrateSetOpt = None,
    plot_format: PlotFormatOpt = "png",
) -> None:
    """Stereo rig self-calibration (paper Sec. 4.4): extrinsic errors per window of frames, per matcher."""
    from e3cm_bench.apps.calibration.run import CalibrationSettings, run_calibration
    from e3cm_bench.matchers import get_matcher
    from e3cm_bench.method.spec import build_method

    given = " ".join(item.strip() for item in settings or [])
    methods = []
    for name in matcher:
        deep = get_matcher(name, allow_import=True).needs_backbone
        label = f"{name} {given}".strip() if deep and given else name
        label = label if backbone == DEFAULT_BACKBONE or not deep else f"{label} [{backbone}]"
        # no benchmark: the one path without one (the side as given, none: full resolution); --set is the deep matchers'
        methods.append(build_method(method_values(dict(matcher=name, backbone=backbone, weights=weights,
                                                       max_side=max_side, seed=seed, label=label,
                                                       settings=settings if deep else None))))
    from e3cm_bench.drawing.formats import plots_as

    with plots_as(plot_format):
        run_calibration(root, out, methods, CalibrationSettings(frames=tuple(frames), seed=seed), device=device,
                        unrectified=unrectified, overwrite=overwrite, console=console)



@app.command()
@friendly_errors
def matchers(
    names: Annotated[
        Optional[list[str]], typer.Argument(help="Only these matchers (names or package.module:factory).")
    ] = None,
) -> None:
    """Every matcher: its origin (built-in, plugin package and version, module), what it is, its settings, defaults."""
    from e3cm_bench.matchers import broken_plugins, entries, get_matcher

    shown = [get_matcher(name, allow_import=True) for name in names] if names else entries()
    for line in describe_matchers(shown):
        say(line)
    for name, why in ([] if names else sorted(broken_plugins().items())):
        say(f"{name}  (not loaded) {why}")


def describe_matchers(shown) -> list[str]:
    """The `matchers` listing: a head line per matcher, then its settings with their defaults."""
    import dataclasses

    from e3cm_bench.matchers import BackboneSettings

    lines = []
    for entry in shown:
        lines.append(f"{entry.name}  ({entry.origin})  {entry.description}")
        if entry.preset_of is not None:
            lines.append(f"    = {entry.preset_of} with " + ", ".join(f"{k}={v}" for k, v in entry.preset.items()))
            continue
        settings = []
        for f in entry.setting_fields():
            if not f.init:
                continue
            default = f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[misc]
            settings.append(f"{f.name}={_setting_text(default)}")
        lines.append("    settings: " + (", ".join(settings) or "none"))
        if entry.needs_backbone:
            net = ", ".join(f"{f.name}={_setting_text(f.default)}" for f in dataclasses.fields(BackboneSettings))
            lines.append(f"    backbone: --backbone, --weights; {net}")
        if entry.model:
            lines.append(
                "    model: --device, --weights FILE (else the library's weights, downloaded into its cache once)"
            )
        if entry.requires:
            lines.append(f"    needs: {', '.join(entry.requires)} ({entry.install_hint()})")
        if entry.shorthands:
            lines.append("    shorthands: " + ", ".join(f"--{n.replace('_', '-')}" for n in entry.shorthands))
        if entry.paper_row:
            lines.append(f"    paper row: {entry.paper_row}")
    return lines


def _setting_text(value) -> str:
    if isinstance(value, (tuple, list)):
        return ",".join(str(v) for v in value)
    if isinstance(value, bool):
        return str(value).lower()
    return "none" if value is None else str(value)


