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


def main() -> None:
    try:
        from e3cm_bench.cli import app
    except KeyboardInterrupt:
        print("error: interrupted (Ctrl-C) while starting; nothing was done", file=sys.stderr)
        raise SystemExit(INTERRUPTED) from None
    except ImportError as exc:  # a broken OpenCV, h5py or PyYAML: one line, even for --help
        from e3cm_bench.ground.library_errors import broken_library_line

        line = None if os.environ.get("E3CM_BENCH_DEBUG") else broken_library_line(exc)
        if line is None:
            raise
        print(line, file=sys.stderr)
        raise SystemExit(2) from None
    app()


if __name__ == "__main__":
    main()
