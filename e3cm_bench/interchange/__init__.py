"""Matches in and out: another tool's files as sources for ``import`` (e3cm_bench.imported runs
them), and ``export_run`` to each format of the registry (registry.py: COLMAP, glue-factory,
hloc, npz, each declared once in its own module with its reader, writer and pixel origin); the
pixel conventions at the boundary live in ``pixels``. docs/interchange.md describes the formats
and their conventions."""

from .base import MAX_POINTS, MissingPair
from .colmap import ColmapSource
from .gluefactory import GluefactorySource
from .hloc import HlocSource, hloc_pair_key
from .npz import NpzSource
from .pixels import ORIGINS, from_origin, half_pixel_check, to_origin
from .registry import Format, formats, get_format, register

__all__ = ["MAX_POINTS", "ORIGINS", "ColmapSource", "Format", "GluefactorySource", "HlocSource", "MissingPair",
           "NpzSource", "export_run", "formats", "from_origin", "get_format", "half_pixel_check", "hloc_pair_key",
           "register", "to_origin"]


def __getattr__(name: str):
    # export_run on first use: export.py loads the run machinery (and h5py), which the command
    # line, reading the format registry through this package, does not need to answer
    if name == "export_run":
        from .export import export_run

        return export_run
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
