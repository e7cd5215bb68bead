"""Matches in and out: another tool's files as sources for ``import`` (e3cm_bench.imported runs
them), and ``export_run`` to COLMAP, hloc, glue-factory and npz; the pixel conventions at the
boundary live in ``pixels``. docs/interchange.md describes the formats and their conventions."""

from .base import MAX_POINTS, MissingPair
from .colmap import ColmapSource
from .export import FORMATS, export_run
from .gluefactory import GluefactorySource
from .hloc import HlocSource, hloc_pair_key
from .npz import NpzSource
from .pixels import ORIGINS, from_origin, half_pixel_check, to_origin

__all__ = ["FORMATS", "MAX_POINTS", "ORIGINS", "ColmapSource", "GluefactorySource", "HlocSource", "MissingPair",
           "NpzSource", "export_run", "from_origin", "half_pixel_check", "hloc_pair_key", "to_origin"]
