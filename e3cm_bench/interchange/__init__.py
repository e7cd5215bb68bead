"""Matches in and out: another tool's files as sources for ``import`` (e3cm_bench.pipeline.imported runs
them), and ``export_run`` to each format of the registry (registry.py: COLMAP, glue-factory,
hloc, npz, each declared once in its own module with its reader, writer and pixel origin); the
pixel conventions at the boundary live in ``pixels``. docs/interchange.md describes the formats
and their conventions."""

from e3cm_bench.interchange.base import MAX_POINTS, MissingPair
from e3cm_bench.interchange.colmap import ColmapSource
from e3cm_bench.interchange.gluefactory import GluefactorySource
from e3cm_bench.interchange.hloc import HlocSource, hloc_pair_key
from e3cm_bench.interchange.npz import NpzSource
from e3cm_bench.interchange.pixels import ORIGINS, from_origin, half_pixel_check, to_origin
from e3cm_bench.interchange.registry import Format, formats, get_format, register

__all__ = ["MAX_POINTS", "ORIGINS", "ColmapSource", "Format", "GluefactorySource", "HlocSource", "MissingPair",
           "NpzSource", "formats", "from_origin", "get_format", "half_pixel_check", "hloc_pair_key",
           "register", "to_origin"]

