"""A method: everything that decides the matches, frozen in one value (`MethodSpec`).

The same object is the identity of a run's cached matches (``identity()`` goes to
config.yaml and is compared before a run resumes) and what builds the matcher
(``build()``). What only changes the metrics lives in `benchmarks.EvalSettings`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from e3cm_bench.backbones.names import DEFAULT_BACKBONE
from e3cm_bench.ground.files import file_sha256
from e3cm_bench.ground.images import RESIZE_MODES
from e3cm_bench.matchers import check_settings, get_matcher, resolve
from e3cm_bench.method.options import METHOD_OPTIONS, check_method_values, resolved_side, with_defaults

# MethodSpec.create's keywords: the method options it takes by their names in the option table
# (their defaults are the table's), and how a protocol frames the images (not a user's option).
CREATE_OPTIONS = ("weights", "estimator", "sampson_px", "ratio", "max_side", "seed", "label")
FRAMING = {"upright": True, "resize": "shrink"}


@dataclass(frozen=True)
class MethodSpec:
    """matcher, backbone, weights (and their hash), matcher settings, resize, seed where random.

    Build one with `MethodSpec.create`, which validates and normalises the options.
    settings: the matcher's own fields (E3CMSettings / DFMSettings) as sorted (key, value)
    pairs, lists turned into tuples, so that the spec is hashable and compares by value.
    max_side: longer side for matching, None = full resolution (already resolved against
    the benchmark's default; what config.yaml records, options.resolved_side). resize: how images are brought to
    max_side (images.RESIZE_MODES:
    shrink, ours; exact, SuperGlue's; exact-div8, LoFTR's). seed: the seed of the matcher's robust estimators, None for
    matchers that draw no random numbers (their matches do not depend on it). upright: match
    images turned upright by their pair list's rot0/rot1 (YFCC, ScanNet; SuperGlue's way).
    plugin: what a matcher from outside this package is, as sorted (key, value) pairs: its
    distribution and version, or its module, with the sha256 of its code (None: built-in).
    label: the name in tables and plots; not part of the identity.
    """

    matcher: str = "e3cm"
    backbone: str | None = DEFAULT_BACKBONE
    weights: str | None = None
    weights_sha256: str | None = None
    settings: tuple[tuple[str, object], ...] = ()
    max_side: int | None = None
    resize: str = "shrink"
    seed: int | None = None
    upright: bool = True
    plugin: tuple[tuple[str, object], ...] | None = None
    label: str = field(default="", compare=False)

    @classmethod
    def create(cls, matcher: str = "e3cm", backbone: str = DEFAULT_BACKBONE, *, available: bool = True,
               **given) -> MethodSpec:
        """Options as a user gives them -> a spec: the matcher, its backbone (the two a caller may
        give in order) and `given`: the other method options by their names in the option table
        (CREATE_OPTIONS of options.METHOD_OPTIONS, each defaulting to its one
        declaration there; `options`: the settings by name) and the protocol's framing (FRAMING:
        upright, resize); another keyword is a TypeError, as for any signature. Each is checked
        against its declaration (one line naming the first of the wrong kind). The shorthands
        ratio, estimator and sampson_px become settings of the matcher where it takes them
        (its registry entry says) and are ignored where not, never guessed. options: further
        settings by name (`--set KEY=VALUE`: e.g. dfm's variant, e3cm's ratio_at, num_levels,
        channel_order); these are checked, and a name the matcher does not have is an error. A
        preset (e3cm-ransac) becomes its matcher with its settings (the same identity, and the
        same default label: e3cm + estimator ransac reads e3cm-ransac). max_side: 0
        (options.FULL_RESOLUTION) or None is full resolution. available=False checks the
        options only (a config's validation): a peer's extra and weights are not looked for,
        and the spec, without their hashes, is not one to run. Commands and configs reach
        this through options.build_method (Benchmark.resolve_method)."""
        unknown = sorted(set(given) - set(CREATE_OPTIONS) - {"options"} - set(FRAMING))
        if unknown:
            raise TypeError(f"MethodSpec.create() got an unexpected keyword argument {unknown[0]!r}")
        v = {**{name: METHOD_OPTIONS[name].default for name in CREATE_OPTIONS}, **FRAMING, **given}
        weights, estimator, sampson_px = v["weights"], v["estimator"], v["sampson_px"]
        ratio, max_side, seed, label, options = v["ratio"], v["max_side"], v["seed"], v["label"], v.get("options")
        upright, resize = v["upright"], v["resize"]
        check_method_values({"matcher": matcher, "backbone": backbone, "weights": weights, "estimator": estimator,
                             "sampson_px": sampson_px, "ratio": ratio, "max_side": max_side, "seed": seed,
                             "label": label or None, "settings": options})
        if resize not in RESIZE_MODES:
            raise ValueError(f"unknown resize {resize!r}; choose one of {', '.join(RESIZE_MODES)}")
        # a preset's own matcher; `matcher` is the user's choice, so module:factory may be imported
        entry, _ = resolve(matcher, {}, allow_import=True)
        shorthands = {"ratio": ratio, "estimator": estimator, "sampson_px": sampson_px}
        entry, settings = resolve(matcher, _given_settings(entry.shorthands, shorthands, options))
        settings = {**entry.recorded, **settings}
        key = entry.name if get_matcher(matcher).preset_of is not None else matcher
        instance = check_settings(key, settings)
        if available:
            entry.check_requirements()
        takes_weights = entry.needs_backbone or entry.model
        spec = cls(
            matcher=key,
            backbone=backbone if entry.needs_backbone else None,
            weights=str(weights) if takes_weights and weights is not None else None,
            weights_sha256=_weights_sha256(entry, instance, weights if takes_weights else None, available),
            settings=tuple(sorted(settings.items())),
            max_side=resolved_side(max_side),
            resize=resize,
            seed=int(seed) if entry.is_random(instance) else None,
            upright=bool(upright),
            plugin=tuple(sorted(entry.source.items())) if entry.source else None,
        )
        return spec.with_label(label or spec.default_label())

    @classmethod
    def from_identity(cls, identity: dict, label: str = "") -> MethodSpec:
        """The spec a run folder recorded (config.yaml `identity`, as identity() wrote it): a
        recorded method is read back, not resolved again from options (its weights' hashes and
        the protocol's choices are in the record). Keys this version does not know are left out."""
        fields = dict(identity)
        settings = fields.pop("settings", None) or {}
        fields["settings"] = tuple(sorted((k, tuple(v) if isinstance(v, list) else v) for k, v in settings.items()))
        if fields.get("plugin") is not None:
            fields["plugin"] = tuple(sorted(dict(fields["plugin"]).items()))
        known = cls.identity_keys()
        return cls(**{k: v for k, v in fields.items() if k in known}, label=label)

    @classmethod
    def identity_keys(cls) -> set[str]:
        """The keys of the `identity` block this version reads."""
        return set(cls.__dataclass_fields__) - {"label"}

    def with_label(self, label: str) -> MethodSpec:
        return MethodSpec(**{**self.identity_fields(), "label": label})

    def identity_fields(self) -> dict:
        return {
            "matcher": self.matcher, "backbone": self.backbone, "weights": self.weights,
            "weights_sha256": self.weights_sha256, "settings": self.settings,
            "max_side": self.max_side, "resize": self.resize, "seed": self.seed, "upright": self.upright,
            "plugin": self.plugin,
        }

    def identity(self) -> dict:
        """What the matches depend on, as plain YAML-ready values (config.yaml `identity`);
        `plugin` only for a matcher from outside this package."""
        fields = self.identity_fields()
        fields["settings"] = {k: list(v) if isinstance(v, tuple) else v for k, v in self.settings}
        if self.plugin is None:
            del fields["plugin"]
        else:
            fields["plugin"] = dict(self.plugin)
        return fields

    def settings_dict(self) -> dict:
        return dict(self.settings)

    def default_label(self) -> str:
        """The matcher's name, then "-backbone" unless the default backbone (vgg19), "-estimator" unless top8,
        "-variant" of dfm unless release: e.g. e3cm-ransac, dfm-densenet161, dfm-corrected."""
        name = get_matcher(self.matcher).name  # package.module:factory -> the factory's matcher name
        label = name if self.backbone in (None, DEFAULT_BACKBONE) else f"{name}-{self.backbone}"
        settings = self.settings_dict()
        estimator = settings.get("estimator", "top8")
        label = label if estimator == "top8" else f"{label}-{estimator}"
        variant = settings.get("variant", "release")
        return label if variant == "release" else f"{label}-{variant}"

    @property
    def seed_for_matching(self) -> int:
        """The value OpenCV's RNG is seeded with before each pair (0 for matchers that draw nothing)."""
        return self.seed or 0

    def build(self, device: str = "cpu", pretrained: bool = True, loaded: dict | None = None):
        """The matcher this spec describes (loads the backbone and its weights; `loaded`: see
        build_matcher)."""
        from e3cm_bench.matchers import build_matcher

        return build_matcher(
            self.matcher,
            self.backbone or DEFAULT_BACKBONE,
            self.weights,
            device,
            pretrained,
            self.settings_dict(),
            loaded=loaded,
        )

    @property
    def folder(self) -> str:
        """The label as a folder name: 'e3cm [efficientnet_lite0]' -> 'e3cm_efficientnet_lite0'."""
        return self.label.replace(" ", "_").replace("[", "").replace("]", "")

    @property
    def resize_description(self) -> str:
        """The size images are matched at, in words."""
        if not self.max_side:
            return "full resolution"
        return {"shrink": f"longer side at most {self.max_side} px",
                "exact": f"longer side exactly {self.max_side} px (enlarged too)",
                "exact-div8": f"longer side exactly {self.max_side} px, sides floored to multiples of 8",
                }[self.resize]

    def describe(self) -> str:
        """One line for the console."""
        net = f" ({self.backbone})" if self.backbone else ""
        seed = f"; seed {self.seed}" if self.seed is not None else ""
        return f"matcher {self.matcher}{net}; resize: {self.resize_description}{seed}"


def build_method(given: Mapping, benchmark=None, device: str = "cpu", available: bool = True,
                 warn: Callable[[str], None] | None = None):
    """The one path from a method's options to its MethodSpec: every command, experiment config
    and Benchmark.resolve_method comes through here.

    given: method options by name (options.METHOD_OPTIONS; numbers as tuples, settings as a mapping),
    the rest taken from the table's defaults. benchmark: the run's; its protocol (``protocol``,
    else the benchmark's default one) gives the side when ``max_side`` is not given (else the
    benchmark's default side), the resize mode, the upright rule and, for deep matchers, the
    settings the reference code used (under the user's). Without a benchmark (`match`,
    `calibrate`): the side as given (None or 0: full resolution), shrink, upright. The side goes
    to MethodSpec.create as written; it records 0 as None (resolved_side).
    precision and channel_order join the settings of deep matchers where they differ from
    fp32 and rgb (so that runs with the defaults keep their identity); precision auto is
    resolved for `device`, and a precision that will be emulated is passed to `warn`."""
    values = with_defaults(given)
    check_method_values(values)
    deep = get_matcher(values["matcher"], allow_import=True).needs_backbone  # the user's: it may import
    settings = deep_settings(values, device, warn) if deep else {}
    settings.update(values["settings"] or {})
    settings.update({name: values[name] for name, option in METHOD_OPTIONS.items()  # a setting by its name
                     if option.concerns == "setting" and values[name] is not None and name not in settings})
    side, upright, resize = values["max_side"], True, "shrink"
    if benchmark is not None:
        from e3cm_bench.method.protocols import get_protocol, resolve_max_side, resolve_protocol

        preset = get_protocol(resolve_protocol(benchmark, values["protocol"]), benchmark.name)
        side = resolve_max_side(benchmark, side, preset.name)
        if deep:
            settings = {**preset.method_options.get(benchmark.name, {}), **settings}
        upright, resize = preset.upright, preset.resize_mode(benchmark.name)
    chosen = {name: values[name] for name in CREATE_OPTIONS if name != "max_side"}
    return MethodSpec.create(values["matcher"], values["backbone"], **chosen, max_side=side,
                             options=settings, upright=upright, resize=resize, available=available)


def deep_settings(values: Mapping, device: str, warn) -> dict:
    """--precision and --channel-order as matcher settings (left out at their defaults)."""
    settings = {}
    precision = values["precision"]
    if precision != "fp32":
        from e3cm_bench.ground.devices import resolve_precision  # torch: only for a precision other than fp32

        precision, warning = resolve_precision(precision, device)
        if warning and warn is not None:
            warn(warning)
        if precision != "fp32":
            settings["precision"] = precision
    if values["channel_order"] != "rgb":
        settings["channel_order"] = values["channel_order"]
    return settings


def identity_changes(before: dict, now: dict) -> list[str]:
    """The keys of a recorded identity (config.yaml) that differ from `now`'s, sorted."""
    # Records written before resize modes existed were all resized the one way there was.
    before = {"resize": "shrink", **before}
    return [k for k in sorted(set(before) | set(now)) if before.get(k) != now.get(k)]


def _given_settings(takes: tuple[str, ...], shorthands: dict, options: dict | None) -> dict:
    """The matcher's settings from the shorthands it takes (`takes`: its registry entry's
    shorthands; the others are ignored) and --set's options (lists as tuples)."""
    settings: dict = {}
    for name in takes:
        value = shorthands[name]
        if value is None:
            continue
        settings[name] = value if name == "estimator" else _numbers(value, name)
        if name == "ratio" and any(not 0 < r <= 1 for r in settings["ratio"]):
            raise ValueError(f"--ratio values must be in (0, 1], got {','.join(map(str, value))}")
    for name, value in (options or {}).items():
        settings[name] = _numbers(value, name) if isinstance(value, (list, tuple)) else value
    return settings


def _weights_sha256(entry, instance, weights, available: bool) -> str | None:
    """The hash of what the matcher loads: the --weights file (and the files a matcher keeps
    beside it), else the library's own files (fetched into its cache first); None when
    `available` is False (a config's validation looks for no file)."""
    if weights is not None:
        path = Path(weights)
        if not path.is_file():
            raise ValueError(f"{path}: weights file not found")
        digest = file_sha256(path)
        if entry.weights_beside is not None and available:
            beside = entry.weights_beside(instance)
            digest = ", ".join([digest] + [f"{f.name}={file_sha256(f.fetch())}" for f in beside])
        return digest
    if entry.weights is not None and available:
        return ", ".join(f"{f.name}={file_sha256(f.fetch())}" for f in entry.weights(instance))
    return None


def _numbers(values, name: str) -> tuple[float, ...]:
    try:
        return tuple(float(v) for v in values)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected numbers, got {values!r}") from None


def parse_numbers(text: str | None, option: str) -> tuple[float, ...] | None:
    """'0.9,0.9,0.95' -> (0.9, 0.9, 0.95), for comma-separated CLI options."""
    if text is None:
        return None
    try:
        return tuple(float(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"{option}: expected comma-separated numbers, got {text!r}") from None


def method_values(given: dict) -> dict:
    """A command's method options as typed -> as method.build_method takes them: the
    comma-separated numbers as tuples, --set's KEY=VALUE items as a mapping; the others as given."""
    values = dict(given)
    for name in ("sampson_px", "ratio"):
        if isinstance(values.get(name), str):
            values[name] = parse_numbers(values[name], METHOD_OPTIONS[name].flags[0])
    if "settings" in values and not isinstance(values["settings"], dict):
        values["settings"] = parse_settings(values["settings"])
    return values


def parse_settings(pairs: list[str] | None) -> dict:
    """['variant=corrected', 'num_levels=4'] -> {'variant': 'corrected', 'num_levels': 4} (YAML
    values). --precision and --channel-order join them in method.build_method (deep_settings)."""
    from e3cm_bench.ground.files import load_yaml_text

    settings = {}
    for item in pairs or []:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--set {item!r}: expected KEY=VALUE")
        settings[key.strip()] = load_yaml_text(value)
    return settings
