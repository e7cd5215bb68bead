"""pycolmap, the optional COLMAP bindings (the colmap extra), imported one way for every
module that needs it: the COLMAP format (interchange/colmap.py), the sfm benchmark, pycolmap's
estimators (geometry/estimators.py) and COLMAP's own SIFT matcher (matchers/colmap_sift.py)."""

from __future__ import annotations


def pycolmap_module():
    """pycolmap, or a one-line ValueError naming the extra that installs it."""
    # PIL's imaging library loaded first: pycolmap 4.2.1 loaded before it makes every PNG that
    # Pillow 13 writes abort the process ("corrupted size vs. prev_size", in zlib's deflateEnd)
    import PIL.Image  # noqa: F401

    try:
        import pycolmap
    except ImportError:
        raise ValueError("this needs pycolmap (COLMAP's bindings): pip install 'e3cm-bench[colmap]'") from None
    return pycolmap


def pycolmap_version() -> str | None:
    """The version a record names (None where pycolmap is not installed)."""
    try:
        return pycolmap_module().__version__
    except ValueError:
        return None
