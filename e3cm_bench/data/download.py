"""`e3cm-bench download`: fetch a benchmark's files (resuming), verify them, unpack them safely.

- Fetching resumes: bytes arrive in ``FILE.part``; a rerun asks the server for the rest
  (an HTTP range request) and starts over where the server refuses ranges, answers a range
  from byte 0, or answers 416 without saying that the part already holds the whole file.
- Complete before trusted: ``FILE.part`` becomes ``FILE`` only when its length is the one the
  server announced (Content-Length, Content-Range), and a 206 must answer the range asked.
  An archive is then unpacked whole (every zip member read to its end against its CRC-32,
  every tar member read through) before its hash is recorded; a damaged one is moved aside
  to ``FILE.bad``, so the next run fetches it again instead of trusting it.
- Verifying: sha256 (and md5 where a source publishes one) against the hash pinned in
  datasets/sources.py; where none is pinned, against the hash recorded in LOCK_FILE beside the
  data by the first complete download. LOCK_FILE is replaced atomically, never left half written.
- Unpacking: into a temporary folder beside the target, renamed into place at the end;
  members with absolute paths, ``..``, links or device files are refused (tar: Python's
  ``data`` filter; zip: checked here), nothing is written outside the target.
- Bounded: a body is cut off past the size a source expects (Part.size with a margin; a part
  that declares none, past UNKNOWN_SIZE_CAP), an archive whose members would unpack to more
  than UNPACK_RATIO times its size is refused, and the disk is never filled below FREE_RESERVE
  (the free disk is also checked before fetching: twice the size for archives).
- Deadlines that a slow server cannot stretch: each file has an overall deadline, from the
  connection to the last byte (scaled to its size, or E3CM_BENCH_DOWNLOAD_DEADLINE seconds),
  the server's answer (status and headers) must arrive within HEADERS_S, and a body that
  delivers fewer than STALL_BYTES in STALL_S is given up on. A watchdog thread shuts the
  connection's socket at the deadline, so that no read (a header trickled a byte at a time,
  a read waiting on a silent server) outlives it. What arrived is kept and resumed from.
- One download at a time per data folder: the folder is locked like a run folder (FolderLock).

Here: the fetching (resume, bounds, deadlines) and each part's steps. The hash record, the
free-space checks and the completeness check of a placed copy are data_folder.py's; unpacking
is archives.py's; the watched connections and the reading of a server's ranges are
download_http.py's.
"""

from __future__ import annotations

import dataclasses
import errno
import http.client
import os
import shutil
import socket
import threading
import time
from pathlib import Path
from urllib.error import HTTPError, URLError
from urllib.request import Request, build_opener

from rich.console import Console
from rich.progress import BarColumn, DownloadColumn, Progress, TextColumn, TimeRemainingColumn, TransferSpeedColumn

# extract, check, find_root and status are read from here too (the command line, tests)
from e3cm_bench.data.archives import extract, place, unpack  # noqa: F401
from e3cm_bench.data.folder import (
    CHUNK,
    FREE_RESERVE,
    LOCK_FILE,
    DownloadError,
    check,  # noqa: F401 - re-exported: the commands and tests call download.check
    check_free_space,
    disk_full,
    find_root,  # noqa: F401 - re-exported: the commands and tests call download.find_root
    read_lock,
    record_hash,
    status,  # noqa: F401 - re-exported: the commands and tests call download.status
    verify,
)
from e3cm_bench.datasets.sources import Part, Source
from e3cm_bench.data.http import WatchedHTTP, WatchedHTTPS, body_range, shut, whole_length
from e3cm_bench.ground.files import refuse_link, write_atomically
from e3cm_bench.ground.locks import FolderLock
from e3cm_bench.ground.folders import remove_folder

TIMEOUT_S = 60  # one read without a byte: the server is gone
# A part's sizes in sources.py are rounded, and hosts re-pack archives: a body may exceed its
# Part.size by this factor plus this slack before it is taken for an endless one.
SIZE_MARGIN = 1.25
SIZE_SLACK = 8 << 20
# The overall deadline: a base for slow starts plus the expected bytes at the slowest average
# rate worth waiting for (1.3 GB: about 3.8 h); where no size is known, a fixed bound.
DEADLINE_BASE_S = 600
MIN_RATE = 100_000
UNKNOWN_SIZE_DEADLINE_S = 4 * 3600
DEADLINE_ENV = "E3CM_BENCH_DOWNLOAD_DEADLINE"  # seconds for one file, replacing the scaled deadline
# A part that declares no size is still cut off here (the largest source file is 1.3 GB).
UNKNOWN_SIZE_CAP = 4 << 30
# The server's status line and headers: a few hundred bytes, which a sound server sends at once.
HEADERS_S = 120
# A body delivering fewer bytes than this in STALL_S seconds is given up on (resumed later):
# 0.5 kB/s, where a 1 byte per 2 s trickle would otherwise hold a download for hours.
STALL_S = 120
STALL_BYTES = 64 << 10


def download(source: Source, to: Path, origin: str | None = None, sha256: str | None = None,
             console: Console | None = None) -> Path:
    """Every part of `source` fetched (or taken from `origin`: a mirror URL or a file already
    downloaded, for a one-part source), verified and placed under to/source.folder; returns
    that folder. The manual steps of a source that a script cannot fetch are raised as one line."""
    console = console or Console()
    to = Path(to)
    target = to / source.folder
    parts = source.parts
    if origin is not None:
        if len(parts) != 1:
            raise DownloadError(f"--from applies to a one-file source; {source.name} has {len(parts) or 'no'} files")
        parts = (dataclasses.replace(parts[0], url=origin, sha256=sha256 or parts[0].sha256),)
    elif sha256 is not None:
        raise DownloadError("--sha256 goes with --from (the hash of the file given there)")
    to.mkdir(parents=True, exist_ok=True)
    # Two downloads into one folder would interleave their .part files, unpacking and hash
    # records (an incomplete copy marked complete): the second is refused in one line.
    with FolderLock(to, option="--to"):
        try:
            read_lock(to)  # a damaged record stops the download before anything is fetched
            for part in parts:
                if part.url is None:
                    continue
                if part.extract and (target / ".complete").is_file():
                    continue
                _fetch_part(part, to, target, console)
        except OSError as error:
            if error.errno != errno.ENOSPC:
                raise
            raise disk_full(Path(error.filename or to), "what was fetched is kept and resumed from") from None
    if source.manual:
        raise DownloadError(f"{source.name}: {source.manual.format(folder=target)}; then check it with "
                            f"e3cm-bench download {source.name} --to {to} --check")
    return target


def _fetch_part(part: Part, to: Path, target: Path, console: Console) -> None:
    """One part fetched, verified, checked whole, recorded, placed (in that order: the hash is
    recorded only for a file that passed every check, and before it is placed, so that a
    placed copy always has its record)."""
    dest = to / ".downloads" / Path(part.file).name if part.extract else target / part.file
    fetched = fetch(part.url, dest, part.size, part.extract, console)
    owned = fetched == dest  # a file given with --from is the user's: never moved aside
    digest = verify(fetched, part, to, owned)
    if part.extract:
        try:
            temporary = unpack(fetched, target, owned)
        except DownloadError as error:
            if part.sha256 or read_lock(to).get(part.file) != digest:
                raise
            # a damaged archive whose hash is on record: recorded by a version that did not check
            # archives, and it would refuse the good file next
            raise DownloadError(f"{error}; its sha256 was recorded in {to / LOCK_FILE} by an earlier download "
                                f"that did not check archives: remove the {part.file!r} entry there first") from None
        try:
            record_hash(to, part, digest)
            place(temporary, target, fetched)
        finally:
            remove_folder(temporary, ignore_errors=True)
    else:
        if not owned:  # a file downloaded by hand is copied into place, leaving the user's own
            dest.parent.mkdir(parents=True, exist_ok=True)
            write_atomically(dest, lambda tmp: shutil.copyfile(fetched, tmp))
        record_hash(to, part, digest)


def fetch(url: str, dest: Path, size: int | None = None, archive: bool = False, console: Console | None = None) -> Path:
    """dest, downloaded from `url` (or a local file's path / file:// URL, used as it is).
    `size`: the expected bytes (Part.size), which bound the body and the time it may take."""
    local = Path(url[len("file://"):]) if url.startswith("file://") else Path(url)
    if "://" not in url or url.startswith("file://"):
        if not local.is_file():
            raise DownloadError(f"{local}: no such file")
        return local
    refuse_link(dest)
    if dest.is_file():
        return dest
    dest.parent.mkdir(parents=True, exist_ok=True)
    part = refuse_link(dest.with_name(dest.name + ".part"))
    cap = max_bytes(size)
    offset = part.stat().st_size if part.exists() else 0
    if offset > cap:  # more than this file can hold: not a beginning of it
        part.unlink()
        offset = 0
    check_free_space(dest.parent, (size or 0) * (2 if archive else 1) - offset)
    with Deadline(url, part, None if size is None else max(0, size - offset)) as deadline:
        response, refused = _open(url, offset, deadline)
        if refused is not None:  # 416: the server has no byte from `offset` on
            if offset == whole_length(refused):
                os.replace(part, dest)  # the server's own size says the part already holds it all
                return dest
            # A part longer than the file, or a server that does not say the file's size: the part
            # cannot be shown to be the file's beginning, so it is dropped and the file fetched whole.
            part.unlink()
            offset = 0
            response, _ = _open(url, 0, deadline)
        with response:
            start, end, total = body_range(url, response, offset, part)
            if total is not None and total > cap:
                raise DownloadError(f"{url}: announces {total} bytes, more than the {cap} this file may have "
                                    f"(about {size} expected); nothing was written: check the URL or the mirror")
            if size is None and total is not None:
                deadline.expect(total - start)
            got = _receive(url, response, part, start, end, cap, deadline, console)
    if (end is not None and got != end) or (total is not None and got != total):
        raise DownloadError(f"{url}: the connection dropped at {got} of {total if total is not None else end} bytes; "
                            f"{part} is kept, rerun the same command to resume")
    os.replace(part, dest)
    return dest


def _open(url: str, offset: int, deadline: Deadline):
    """(the server's answer to a GET from byte `offset`, None), or (None, the HTTPError) for a
    416 to a resumed request, whose Content-Range may say the file's length. The answer must
    come within HEADERS_S (and the overall deadline): the watchdog shuts the socket otherwise."""
    request = Request(url, headers={"Range": f"bytes={offset}-"} if offset else {})
    opener = build_opener(WatchedHTTP(deadline), WatchedHTTPS(deadline))
    deadline.phase(HEADERS_S, "sent no complete answer (status line and headers)")
    try:
        response = opener.open(request, timeout=min(TIMEOUT_S, max(deadline.left(), 0.1)))  # noqa: S310 - sources.py or --from
        return response, None
    except HTTPError as error:
        if error.code == 416 and offset:
            return None, error
        raise DownloadError(f"{url}: HTTP {error.code} {error.reason}") from None
    except (URLError, OSError, http.client.HTTPException) as error:
        deadline.check()  # a socket the watchdog shut: the deadline's line, not "cannot connect"
        reason = getattr(error, "reason", error)
        raise DownloadError(
            f"{url}: cannot connect ({reason}); check the network or pass --from MIRROR_OR_FILE"
        ) from None
    finally:
        deadline.phase(None)


class Deadline:
    """A file's overall deadline (and a shorter one for a phase, the server's answer), held by
    a watchdog thread that shuts every socket the download opened once one passes: a read
    blocked on a server that trickles or says nothing then returns at once, and check()
    raises the deadline's one line. A context manager: leaving it stops the watchdog."""

    def __init__(self, url: str, part: Path, expected: int | None) -> None:
        self.url, self.part = url, part
        self.started = time.monotonic()
        self.seconds = deadline_seconds(expected)
        self._phase: tuple[float, str, float] | None = None
        self._sockets: list[socket.socket] = []
        self._lock = threading.Lock()
        self._done = threading.Event()
        self.passed = ""  # why the watchdog shut the sockets

    def __enter__(self) -> Deadline:
        threading.Thread(target=self._watch, name="download-deadline", daemon=True).start()
        return self

    def __exit__(self, *exc) -> None:
        self._done.set()

    def expect(self, remaining: int) -> None:
        """The size became known (Content-Length): the scaled deadline from it, unless set by hand."""
        if not os.environ.get(DEADLINE_ENV):
            self.seconds = deadline_seconds(remaining)

    def phase(self, seconds: float | None, what: str = "") -> None:
        self._phase = None if seconds is None else (time.monotonic() + seconds, what, seconds)

    def left(self) -> float:
        return self.started + self.seconds - time.monotonic()

    def watch(self, sock: socket.socket) -> None:
        with self._lock:
            self._sockets.append(sock)
        if self.passed:
            shut(sock)

    def reason(self) -> str:
        if self.left() < 0:
            how = "set by " + DEADLINE_ENV if os.environ.get(DEADLINE_ENV) else \
                f"{MIN_RATE // 1000} kB/s on average; {DEADLINE_ENV}=SECONDS sets another"
            return f"not finished after {self.seconds:.0f} s (the deadline: {how})"
        if self._phase is not None and time.monotonic() > self._phase[0]:
            return f"{self._phase[1]} within {self._phase[2]:.0f} s"
        return ""

    def check(self, got: int | None = None) -> None:
        """The deadline's one line where one has passed (the watchdog's, or found here first)."""
        reason = self.passed or self.reason()
        if reason:
            arrived = f" ({got} bytes arrived)" if got is not None else ""
            kept = f"{self.part} is kept: rerun the same command to resume" if self.part.exists() else \
                "nothing was written: rerun the same command"
            raise DownloadError(f"{self.url}: {reason}{arrived}; {kept}, or pass --from a faster mirror")

    def _watch(self) -> None:
        while not self._done.wait(0.1):
            reason = self.reason()
            if reason:
                self.passed = reason
                with self._lock:
                    for sock in self._sockets:
                        shut(sock)
                return


def _receive(url: str, response, part: Path, start: int, end: int | None, cap: int, deadline: Deadline,
             console: Console | None) -> int:
    """The body written into `part` from byte `start` on; returns the part's length. Stops at
    `cap`, at the deadline, on a stalled body and at FREE_RESERVE, each with one line; a dropped
    connection ends the loop quietly (the caller compares the length with what was announced).
    The progress bar is labelled with the file's name (the part's, less .part)."""
    label = part.name.removesuffix(".part")
    flags = os.O_WRONLY | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC | (os.O_APPEND if start else os.O_TRUNC)
    got = start
    window = (time.monotonic(), got)  # when the current stall window began, and the bytes then
    fd = os.open(part, flags, 0o666)
    try:
        with _progress(console) as progress:
            task = progress.add_task(label, total=end, completed=start)
            while True:
                deadline.check(got)
                now = time.monotonic()
                if now - window[0] >= STALL_S:
                    if got - window[1] < STALL_BYTES:
                        raise DownloadError(f"{url}: {got - window[1]} bytes in the last {now - window[0]:.0f} s "
                                            f"(fewer than {STALL_BYTES} in {STALL_S} s: stalled; {got} bytes arrived); "
                                            f"{part} is kept: rerun the same command to resume, or pass --from a "
                                            "faster mirror")
                    window = (now, got)
                try:
                    # read1: whatever has arrived, so that a trickling server cannot hold one
                    # call past the deadline (read(n) waits for all n bytes)
                    chunk = response.read1(CHUNK)
                except (OSError, http.client.HTTPException):
                    deadline.check(got)  # the watchdog shut the socket
                    break  # the connection dropped: what arrived is kept
                if not chunk:
                    deadline.check(got)
                    break
                if got + len(chunk) > min(cap, end if end is not None else cap):
                    os.close(fd)
                    fd = -1
                    part.unlink(missing_ok=True)
                    limit = min(cap, end) if end is not None else cap
                    raise DownloadError(f"{url}: sent more than the {limit} bytes this file may have; nothing is kept: "
                                        "check the URL or the mirror")
                free = shutil.disk_usage(part.parent).free
                if free - len(chunk) < FREE_RESERVE:
                    raise disk_full(
                        part.parent, f"the {got} bytes that arrived in {part.name} are kept and resumed from", free
                    )
                _write_all(fd, chunk)
                got += len(chunk)
                progress.advance(task, len(chunk))
    finally:
        if fd >= 0:
            os.close(fd)
    return got


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def max_bytes(size: int | None) -> int:
    """The most bytes a part may have: its expected size with a margin; where none is known,
    UNKNOWN_SIZE_CAP (and the free-space floor in _receive, as the disk fills)."""
    if size is None:
        return UNKNOWN_SIZE_CAP
    return int(size * SIZE_MARGIN) + SIZE_SLACK


def deadline_s(expected: int | None) -> float:
    return UNKNOWN_SIZE_DEADLINE_S if expected is None else DEADLINE_BASE_S + expected / MIN_RATE


def deadline_seconds(expected: int | None) -> float:
    """One file's overall deadline: E3CM_BENCH_DOWNLOAD_DEADLINE where set, else scaled to the
    bytes expected (deadline_s)."""
    text = os.environ.get(DEADLINE_ENV)
    if not text:
        return deadline_s(expected)
    try:
        seconds = float(text)
    except ValueError:
        seconds = float("nan")
    if not (seconds > 0 and seconds != float("inf")):
        raise DownloadError(f"{DEADLINE_ENV}={text!r}: expected a positive number of seconds")
    return seconds


def _progress(console: Console | None) -> Progress:
    return Progress(TextColumn("[bold]{task.description}"), BarColumn(), DownloadColumn(), TransferSpeedColumn(),
                    TextColumn("ETA"), TimeRemainingColumn(), console=console or Console())

