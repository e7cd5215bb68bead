"""A library e3cm-bench imports that cannot be imported (a broken OpenCV, h5py, PyYAML or torch
wheel, or one missing): one line naming it, at startup (__main__) and in a command
(cli/common.friendly_errors), where an ImportError in e3cm-bench's own code keeps its traceback.
Imports nothing itself: it runs when the command line's own imports have failed."""

from __future__ import annotations

# pip's names of the libraries whose import name differs
PIP_NAMES = {"cv2": "opencv-python-headless", "yaml": "pyyaml", "PIL": "pillow", "sklearn": "scikit-learn"}


def broken_library(exc: ImportError) -> str | None:
    """The library (top-level name) outside e3cm-bench whose import raised `exc`: the first frame
    of its traceback outside e3cm_bench and importlib, else the module the error names; None
    where the import failed in e3cm-bench's own code (a bug: its traceback is kept)."""
    tb = exc.__traceback__
    while tb is not None:
        module = str(tb.tb_frame.f_globals.get("__name__", ""))
        if module and not module.startswith(("e3cm_bench", "importlib", "__main__")):
            return module.split(".")[0]
        tb = tb.tb_next
    name = (exc.name or "").split(".")[0]
    return name if name and name != "e3cm_bench" else None


def broken_library_line(exc: ImportError) -> str | None:
    """One line for an ImportError of a library e3cm-bench imports (broken or missing), or None."""
    library = broken_library(exc)
    if library is None:
        return None
    reason = " ".join(f"{type(exc).__name__}: {exc}".split())[:300]
    return (
        f"error: the library {library} could not be imported ({reason}); reinstall it "
        f"(pip install --force-reinstall {PIP_NAMES.get(library, library)}), or set E3CM_BENCH_DEBUG=1 to see where"
    )
