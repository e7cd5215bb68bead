"""A run folder's lock, and the check that a folder can hold a run: one process at a time writes
a folder (FolderLock), and a folder that cannot be written is said before any work starts."""

from __future__ import annotations

import errno
import fcntl
import json
import os
import socket
import stat
import sys
import time
from pathlib import Path

from e3cm_bench.ground.files import refuse_link

def writable_folder(folder: Path, create: bool = True) -> Path:
    """`folder`, created if needed (create=False: only checked, so that a command failing
    later leaves nothing behind); a ValueError in one line where it names a file, cannot be
    created, or cannot be written to."""
    folder = Path(folder)
    existing = next((p for p in [folder, *folder.parents] if p.exists()), None)
    if existing is not None and not existing.is_dir():
        raise ValueError(f"{existing}: is a file, not a folder; choose another --out")
    if not create:
        if existing is not None and not os.access(existing, os.W_OK | os.X_OK):
            what = f"cannot create the folder ({existing} is not writable)" if existing != folder else "not writable"
            raise ValueError(f"{folder}: {what}; choose another --out or make it writable")
        return folder
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise ValueError(f"{folder}: cannot create the folder ({error.strerror}); choose another --out") from None
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ValueError(f"{folder}: the folder is not writable; choose another --out or make it writable")
    return folder


class FolderLock:
    """An exclusive lock on a run folder, held while a run reads and writes it.

    flock on ``<folder>/.lock``: the OS releases it when the process ends, however it ends,
    so a killed run never leaves a stale lock. The holder (pid, host, start, command) is
    written into the file, so a second run can say who holds the folder. The file is removed
    when the lock is released (a finished folder holds no holder's record; a killed run's file
    stays, unlocked, and the next run takes it); a run that opened the file just before it
    was removed finds its lock on a file no longer in the folder, and opens the new one.
    """

    def __init__(self, folder: str | Path, option: str = "--out") -> None:
        self.path = Path(folder) / ".lock"
        self.option = option  # the option that named the folder (download's is --to), for the advice
        self._fd: int | None = None

    def __enter__(self) -> FolderLock:
        writable_folder(self.path.parent)
        while not self._take():  # the file was removed by its last holder between open and flock
            pass
        return self

    def _take(self) -> bool:
        # O_NOFOLLOW: a `.lock` that is a link (to a user's file, or dangling) is refused, never
        # truncated or created through; a file with other names (hard links) likewise.
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK, 0o666)
        except OSError as error:
            if error.errno == errno.ELOOP:
                refuse_link(self.path)
            raise
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode) or info.st_nlink != 1:
            os.close(fd)
            what = ("not a regular file" if not stat.S_ISREG(info.st_mode)
                    else f"a file with {info.st_nlink} names (hard links)")
            raise ValueError(f"{self.path}: is {what}; e3cm-bench writes its lock only into a file of its own: "
                             f"remove it or choose another {self.option}")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 4096).decode("utf-8", "replace")
            os.close(fd)
            raise self.busy_error(holder) from None
        try:
            now = os.stat(self.path, follow_symlinks=False)
        except FileNotFoundError:
            now = None
        if now is None or (now.st_dev, now.st_ino) != (info.st_dev, info.st_ino):
            os.close(fd)
            return False
        os.ftruncate(fd, 0)
        holder = {"pid": os.getpid(), "host": socket.gethostname(), "started": time.strftime("%Y-%m-%d %H:%M:%S"),
                  "command": " ".join(sys.argv)}
        os.write(fd, json.dumps(holder).encode())
        self._fd = fd
        _HELD_LOCKS.add(fd)
        return True

    def busy_error(self, holder: str) -> ValueError:
        return ValueError(f"{self.path.parent}: another run is using this folder ({_describe_holder(holder)}); "
                          f"wait for it to finish or choose another {self.option}")

    def __exit__(self, *exc) -> None:
        if self._fd is not None:
            try:
                self.path.unlink()  # while still held: whoever opens it next checks that it is still there
            except OSError:
                pass  # a folder that became read-only or vanished: the lock is released all the same
            _HELD_LOCKS.discard(self._fd)
            os.close(self._fd)  # closing releases the flock
            self._fd = None


# Held folder locks, closed in a forked child: its flock(LOCK_UN) would release the parent's lock.
_HELD_LOCKS: set[int] = set()
os.register_at_fork(after_in_child=lambda: [os.close(fd) for fd in _HELD_LOCKS] and _HELD_LOCKS.clear())


def _describe_holder(text: str) -> str:
    try:
        holder = json.loads(text)
        return f"pid {holder['pid']} on {holder['host']} since {holder['started']}: {holder['command']}"
    except (ValueError, KeyError, TypeError):
        return "holder unknown"
