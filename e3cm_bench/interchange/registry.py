"""The interchange formats, one class each: its name (the flag ``import --NAME`` and the value
``export --to NAME``), its reader (the source ``import`` reads pairs from), its writer (what
``export`` writes), its own pixel origin and the help the command line shows for it.

A format is declared once, in its own module of this package, by a ``Format`` subclass under
``@register``; ``formats()`` imports every module of the package but its MACHINERY, so that a new module is a new
format for ``import``, ``export --to`` and the docs' list without another file naming it.
Nothing here imports h5py or pycolmap: the command line reads this registry to build its options.
"""

from __future__ import annotations

import importlib
import pkgutil
from pathlib import Path

from e3cm_bench.interchange.pixels import check_origin

FORMATS: dict[str, Format] = {}
_discovered = False
# The package's shared machinery, not formats: every other module of it is imported to find them.
MACHINERY = ("base", "export", "pixels", "registry", "tracks")

# File names that say nothing of the method (the formats' usual names, and what `export`
# writes): a source so named is labelled by the folder that holds it.
GENERIC_STEMS = ("matches", "features", "predictions", "database")


class Format:
    """One interchange format. Subclasses set the class attributes and the two methods."""

    name: str = ""
    origin: str = ""  # the format's own pixel origin, "center" or "corner" (pixels.py); stated only here
    reads: tuple[str, ...] = ()  # what `import --NAME` takes, one placeholder per path
    import_help: str = ""
    writes: str = ""  # what `export --to NAME` writes, for its help
    outputs: tuple[str, ...] = ()  # the files export writes into OUT
    merges: bool = False  # one keypoint list per image (tracks.merge_keypoints; --merge-px applies)
    stores_geometry: bool = False  # each pair's two-view geometry (the evaluation's estimate)
    labelled_by: str = ""  # the source's attribute (a path) whose name labels an imported run

    def source(self, paths: tuple[Path, ...], benchmark: str, origin: str | None = None):
        """The reader of these files for `benchmark`, in `origin` (None: the format's own)."""
        raise NotImplementedError

    def write(self, out: Path, items: list, origin: str, job) -> list[Path]:
        """Write base.ExportItem's into OUT in `origin`; job: export.ExportJob (the run's
        benchmark, root, options, merge_px and merged keypoints). Returns the files written."""
        raise NotImplementedError

    def check_available(self) -> None:
        """Raise a one-line ValueError where an optional library the format needs is missing."""

    def targets(self, out: Path, pair_names: list[str]) -> list[Path]:
        """The files an export of these pairs writes (checked before anything is written)."""
        return [out / name for name in self.outputs]

    def label(self, source) -> str:
        """An imported run's method label: the name of the file that labels it, or of the folder
        holding it where that name is one of the formats' usual ones (GENERIC_STEMS)."""
        path = Path(getattr(source, self.labelled_by))
        name = self.label_stem(path)
        if name in GENERIC_STEMS or not name:
            name = path.resolve().parent.name
        return name

    def label_stem(self, path: Path) -> str:
        return path.stem


def register(cls: type[Format]) -> type[Format]:
    """Class decorator: add the format (by its name) to the registry."""
    if not cls.name.isidentifier():
        raise ValueError(f"a format's name becomes a command-line flag and a parameter: {cls.name!r} is not one")
    check_origin(cls.origin)
    FORMATS[cls.name] = cls()
    return cls


def formats() -> dict[str, Format]:
    """Every format, name -> Format: those of this package's modules (each imported once) and any
    registered from elsewhere."""
    global _discovered
    if not _discovered:
        _discovered = True
        package = importlib.import_module(__package__)
        for module in pkgutil.iter_modules(package.__path__):
            if module.name not in MACHINERY and not module.name.startswith("_"):
                importlib.import_module(f"{__package__}.{module.name}")
    return dict(sorted(FORMATS.items()))  # by name: the order does not hang on which module loaded first


def get_format(name: str) -> Format:
    known = formats()
    if name not in known:
        raise ValueError(f"--to must be one of {', '.join(known)}, got {name!r}")
    return known[name]


def source_label(source) -> str:
    """An imported run's method label when --label is not given: the name its maker gave the
    source, since no format records the method (Format.label; npz: the folder's name, hloc: the
    matches file's without hloc's "matches-" prefix); a source of another kind (the Python
    API): imported-<its format>."""
    fmt = formats().get(source.format)
    if fmt is None or not fmt.labelled_by:
        return f"imported-{source.format}"
    return fmt.label(source) or f"imported-{source.format}"


def origin_help() -> str:
    """Each format's own pixel origin, for --pixel-origin's help: 'colmap, gluefactory: corner; ...'."""
    by_origin: dict[str, list[str]] = {}
    for fmt in formats().values():
        by_origin.setdefault(fmt.origin, []).append(fmt.name)
    return "; ".join(f"{', '.join(names)}: {origin}" for origin, names in by_origin.items())
