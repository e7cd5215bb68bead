"""Evaluation protocols: the small sets of settings under which each reference code reports.

Numbers that do not reproduce usually differ in resize, RANSAC threshold, image rotation
or failure handling, not in the matcher. `--protocol NAME` picks one of these presets; its
name and every setting it changes are written to config.yaml (and a non-standard protocol
is flagged in every table).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from e3cm_bench.method.options import FULL_RESOLUTION
from e3cm_bench.ground.suggest import did_you_mean
from e3cm_bench.ground.moved import renamed


@dataclass(frozen=True)
class ReferenceProtocol:
    """benchmarks: those the protocol is defined for; empty: every benchmark. max_side:
    {benchmark: longer side for matching, None = full resolution}; a benchmark not listed
    keeps its own default. resize: {benchmark: how images are brought to that side,
    images.RESIZE_MODES}; not listed: shrink (ours). method_options: deep-matcher settings the reference
    code used (num_levels, channel_order), per benchmark. drop_failures: pairs whose pose
    could not be estimated leave the AUC (instead of counting with error inf). upright:
    turn images upright by the pair list's rot0/rot1 before matching (keypoints are mapped
    back to the stored images). evaluation: {benchmark: EvalSettings fields the reference's
    evaluation sets}. standard: False flags every table row it produced. rotation_error: how
    the pose benchmarks measure the rotation's error (geometry.ROTATION_ERRORS): the presets of
    reference code keep its formula, the default measures to the nearest rotation."""

    name: str
    description: str
    benchmarks: tuple[str, ...]
    max_side: dict = field(default_factory=dict)
    resize: dict = field(default_factory=dict)
    method_options: dict = field(default_factory=dict)
    drop_failures: bool = False
    upright: bool = True
    evaluation: dict = field(default_factory=dict)
    standard: bool = True
    rotation_error: str = "nearest-rotation"
    # The RANSAC seeds a run's interval holds: a reference's evaluation runs once (1); None: the
    # benchmark's own default (Benchmark.default_interval_seeds), e3cm-bench's protocol.
    interval_seeds: int | None = 1
    notes: dict = field(default_factory=dict)  # {benchmark: what the protocol does there}, after the description

    def resize_mode(self, benchmark: str) -> str:
        return self.resize.get(benchmark, "shrink")

    def line(self, benchmark: str | None = None) -> str:
        """What a run prints before it starts, so that the settings behind its numbers are on screen:
        of a benchmark's run, what applies to it only (no word of YFCC on HPatches)."""
        if benchmark is None:
            notes = [f"{name}: {note}" for name, note in self.notes.items()]
            return f"protocol {self.name}: " + "; ".join([self.description, *notes])
        note = self.notes.get(benchmark)
        return f"protocol {self.name} on {benchmark}: {self.description}" + (f"; {note}" if note else "")

    def eval_fields(self, benchmark: str) -> dict:
        """The EvalSettings fields this protocol sets on `benchmark`."""
        return {"protocol": self.name, "drop_failures": self.drop_failures, **self.evaluation.get(benchmark, {})}


PROTOCOLS: dict[str, ReferenceProtocol] = {
    p.name: p
    for p in [
        ReferenceProtocol(
            "default",
            "e3cm-bench's own (docs/benchmarks.md, Protocols)",
            (),  # it sets nothing of its own, so it holds for every benchmark, a newly added one too
            interval_seeds=None,
            notes={
                "hpatches": "images at full size",
                "megadepth": "longer side at most 1200; failures count with error inf",
                "yfcc": "longer side at most 1200; failures count with error inf; images turned upright",
            },
        ),
        ReferenceProtocol(
            "wxbs",
            "wxbs-benchmark's example estimators (its README): OpenCV USAC_MAGSAC (MAGSAC++), confidence "
            "0.999, 100000 iterations; a failed estimate scores 0",
            ("wxbs", "evd"),
            notes={"wxbs": "F at 0.25 px", "evd": "H at 0.5 px"},
            evaluation={
                "wxbs": {
                    "opencv_method": "magsac",
                    "fundamental_ransac_px": 0.25,
                    "fundamental_confidence": 0.999,
                    "fundamental_max_iters": 100000,
                },
                "evd": {
                    "opencv_method": "magsac",
                    "homography_ransac_px": 0.5,
                    "homography_confidence": 0.999,
                    "homography_max_iters": 100000,
                },
            },
        ),
        ReferenceProtocol(
            "loftr",
            "LoFTR's MegaDepth-1500 test config: longer side resized to 840 px (enlarged too), each side then "
            "floored to a multiple of 8, bilinear",
            ("megadepth",),
            max_side={"megadepth": 840},
            resize={"megadepth": "exact-div8"},
            rotation_error="reference",
        ),
        ReferenceProtocol(
            "superglue",
            "SuperGlue's YFCC evaluation (match_pairs.py --resize 1600): images turned upright by rot0/rot1, "
            "longer side resized to 1600 px (enlarged too), bilinear; essential-matrix RANSAC at 1 px of the resized "
            "images",
            ("yfcc",),
            max_side={"yfcc": 1600},
            resize={"yfcc": "exact"},
            evaluation={"yfcc": {"pose_ransac_px": 1.0, "pose_ransac_frame": "matched"}},
            rotation_error="reference",
        ),
        ReferenceProtocol(
            "gluefactory",
            "glue-factory's evaluation",
            ("megadepth", "hpatches"),
            notes={
                "megadepth": "its official LightGlue configs: longer side resized to 1600 px (enlarged too), PoseLib's "
                "relative pose at 2 px of the resized images (its README's command)",
                "hpatches": "gluefactory/eval/hpatches.py and eval/utils.py: the ground-truth H applied to "
                "corner-convention coordinates, glue-factory's match precision prec@1px/prec@3px "
                "(symmetric H error strictly below t; mprec: its median over pairs), PoseLib's H at 1 px, "
                "corner error on the corners (0, 0)..(w, h); its 480 px short-side resize is not applied: "
                "the errors are in the run's pixels",
            },
            max_side={"megadepth": 1600},
            resize={"megadepth": "exact"},
            evaluation={
                "megadepth": {"estimator": "poselib", "pose_ransac_px": 2.0, "pose_ransac_frame": "matched"},
                "hpatches": {
                    "homography_pixel_origin": "corner",
                    "match_precision_px": (1.0, 3.0),
                    "estimator": "poselib",
                    "homography_ransac_px": 1.0,
                },
            },
            rotation_error="reference",
        ),
        ReferenceProtocol(
            "e3cm-release",
            "the E3CM release's eval scripts: full resolution, BGR input, 4 levels (match_small_img) on "
            "the pose benchmarks, failed pairs dropped from the AUC (non-standard)",
            ("hpatches", "megadepth", "yfcc"),
            max_side={"hpatches": FULL_RESOLUTION, "megadepth": FULL_RESOLUTION, "yfcc": FULL_RESOLUTION},
            method_options={
                "hpatches": {"channel_order": "bgr"},
                "megadepth": {"channel_order": "bgr", "num_levels": 4},
                "yfcc": {"channel_order": "bgr", "num_levels": 4},
            },
            drop_failures=True,
            standard=False,
            rotation_error="reference",
        ),
    ]
}


def rotation_error(protocol: str) -> str:
    """How a run under `protocol` (its evaluation.protocol) measures rotation errors; an unknown
    name (a record from elsewhere) gets the default's."""
    return PROTOCOLS.get(protocol, PROTOCOLS["default"]).rotation_error


def resolve_protocol(benchmark, given: str | None) -> str:
    """The protocol's name of a run on `benchmark` (a Benchmark, read for its name and
    default_protocol): the one given, else the benchmark's default (its reference code's where
    it has one: wxbs on WxBS and EVD; else e3cm-bench's own). The one place that default is
    read: every command, `reproduce`, `import` and the Python API (build_method,
    Benchmark.resolve_eval) come through here, so that a config without `protocol:` gets the
    protocol its command gets. get_protocol checks the name."""
    return given or benchmark.default_protocol


def resolve_max_side(benchmark, given: int | None, protocol: str | None = None) -> int | None:
    """The longer side a run on `benchmark` matches at, as given (0, FULL_RESOLUTION: the images
    as stored), else the side `protocol` (None: the benchmark's default one) sets for the benchmark,
    else the benchmark's default_max_side. The one place that default is read (build_method,
    Benchmark.max_side, `reconstruct`); MethodSpec.create records 0 as None (options.resolved_side)."""
    if given is not None:
        return given
    preset = get_protocol(resolve_protocol(benchmark, protocol), benchmark.name)
    return preset.max_side.get(benchmark.name, benchmark.default_max_side)


def get_protocol(name: str, benchmark: str) -> ReferenceProtocol:
    if name not in PROTOCOLS:
        raise ValueError(
            f"unknown protocol {name!r}{did_you_mean(name, PROTOCOLS)}; choose one of {', '.join(PROTOCOLS)}"
        )
    protocol = PROTOCOLS[name]
    if protocol.benchmarks and benchmark not in protocol.benchmarks:
        raise ValueError(f"protocol {name!r} is defined for {', '.join(protocol.benchmarks)}, not {benchmark}")
    return protocol


def __getattr__(name: str):
    return renamed(__name__, name)  # a name renamed here (ground/moved.py RENAMED), else AttributeError
