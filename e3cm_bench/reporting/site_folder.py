"""A report's folder (`e3cm-bench report --out`): which folder a report may be written into
(an empty one, or a report's, told by its MARKER file) and how the new site replaces the old one
whole (built beside it, swapped in at once, signals held off while it moves).
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import os
import signal
import tempfile
import threading
from pathlib import Path

MARKER = ".e3cm-bench-report"  # in every report folder: what a later report may replace
REPORT_ENTRIES = {MARKER, "index.html", "runs", "pairs", "img"}


def report_target(out: Path) -> Path:
    """`out` as an absolute path, or a one-line ValueError where a report may not replace it: a
    link, a file, or a folder holding anything a report did not write (run folders, a user's
    photos). An empty or missing folder is free; one with MARKER and report entries only is a
    previous report."""
    out = Path(os.path.abspath(out))
    if out.is_symlink():
        raise ValueError(f"{out}: is a symbolic link (to {os.readlink(out)}); give the report's folder itself as --out")
    if not out.exists():
        return out
    if not out.is_dir():
        raise ValueError(f"{out}: is a file, not a folder; choose another --out")
    entries = sorted(os.listdir(out))
    if not entries:
        return out
    marker = out / MARKER
    if not marker.is_file() or marker.is_symlink():
        shown = ", ".join(entries[:3]) + (", ..." if len(entries) > 3 else "")
        raise ValueError(f"{out}: not empty and not a report folder (it holds {shown}); a report replaces only a "
                         "folder it wrote itself: choose a new or empty --out")
    foreign = [e for e in entries if e not in REPORT_ENTRIES]
    if foreign:
        raise ValueError(f"{out}: a report folder that also holds {', '.join(foreign[:3])}, which a report did not "
                         "write; move it away or choose another --out")
    return out


def swap_in(built: Path, target: Path) -> None:
    """`built` becomes `target`; the previous report, if any, is left at `built` (to be removed).
    SIGINT and SIGTERM wait until it is done, so that no signal leaves the target half moved."""
    blocked = {signal.SIGINT, signal.SIGTERM}
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, blocked)
    try:
        report_target(target)  # again: files may have been put there while the report was built
        if not os.path.lexists(target):
            os.rename(built, target)
        elif not os.listdir(target):
            # A folder the user made (a shell may stand in it): keep it, move the report in, marker first.
            for name in [MARKER, *sorted(set(os.listdir(built)) - {MARKER})]:
                os.rename(built / name, target / name)
        elif not _exchange(built, target):
            aside = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".report-old", dir=target.parent))
            os.rename(target, aside / "previous")
            os.rename(built, target)
            os.rename(aside, built)
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def _exchange(a: Path, b: Path) -> bool:
    """Swap two folders in one step (Linux renameat2 RENAME_EXCHANGE); False where that is not
    available, and the caller renames twice."""
    try:
        renameat2 = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return False
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    at_fdcwd, rename_exchange = -100, 2
    if renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0:
        return True
    error = ctypes.get_errno()
    if error in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):
        return False
    raise OSError(error, os.strerror(error), str(b))


class _Terminated(SystemExit):
    """SIGTERM while a report is built: unwinds, so that the half-built folder is removed."""


@contextlib.contextmanager
def terminate_as_exception():
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def terminate(signum, frame):
        raise _Terminated(128 + signum)

    previous = signal.signal(signal.SIGTERM, terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
