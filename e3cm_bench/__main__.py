"""The `e3cm-bench` command's entry point (pyproject [project.scripts]), and `python -m e3cm_bench`.

The command line's modules take seconds to import (OpenCV, pandas, typer). A Ctrl-C in that
time would end in a KeyboardInterrupt traceback; here it ends in one line and the usual exit
status of an interrupted command (130). The package's own import is light (__init__ imports
its public names lazily), so this function runs before anything slow is loaded.
"""

from __future__ import annotations

import os
import sys

INTERRUPTED = 130  # 128 + SIGINT, what a shell reports for a command ended by Ctrl-C


# pip's names of the libraries whose import name differs
PIP_NAMES = {"cv2": "opencv-python-headless", "yaml": "pyyaml", "PIL": "pillow", "sklearn": "scikit-learn"}


def broken_library(exc: ImportError) -> str | None:
    """The library (top-level name) outside e3cm-bench whose import raised `exc`: the first frame
    of its traceback outside e3cm_bench and importlib, else the module the error names; None
    where the import failed in e3cm-bench's own code (a bug: its traceback is kept)."""
    tb = exc.__traceback__
    while tb is not None:
        module = str(tb.tb_frame.f_globals.get("__name__", ""))
        if module and not module.startswith(("e3cm_bench", "importlib", "__main__", "typer", "click")):
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
    return (f"error: the library {library} could not be imported ({reason}); reinstall it "
            f"(pip install --force-reinstall {PIP_NAMES.get(library, library)}), or set E3CM_BENCH_DEBUG=1 to see where")


def main() -> None:
    try:
        from .cli import app
    except KeyboardInterrupt:
        print("error: interrupted (Ctrl-C) while starting; nothing was done", file=sys.stderr)
        raise SystemExit(INTERRUPTED) from None
    except ImportError as exc:  # a broken OpenCV, h5py or PyYAML: one line, even for --help
        line = None if os.environ.get("E3CM_BENCH_DEBUG") else broken_library_line(exc)
        if line is None:
            raise
        print(line, file=sys.stderr)
        raise SystemExit(2) from None
    app()


if __name__ == "__main__":
    main()
