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
"""

from __future__ import annotations

import dataclasses
import errno
import hashlib
import http.client
import json
import lzma
import os
import re
import shutil
import socket
import stat
import tarfile
import threading
import time
import zipfile
import zlib
from pathlib import Path, PurePosixPath
from urllib.error import HTTPError, URLError
from urllib.request import HTTPHandler, HTTPSHandler, Request, build_opener

from rich.console import Console
from rich.progress import BarColumn, DownloadColumn, Progress, TextColumn, TimeRemainingColumn, TransferSpeedColumn

from .datasets.sources import Part, Source
from .files import FolderLock, refuse_link, write_atomically

LOCK_FILE = "e3cm-bench-data.lock"
CHUNK = 1 << 20
TIMEOUT_S = 60  # one read without a byte: the server is gone
# A part's sizes in sources.py are rounded, and hosts re-pack archives: a body may exceed its
# Part.size by this factor plus this slack before it is taken for an endless one.
SIZE_MARGIN = 1.25
SIZE_SLACK = 8 << 20
# Image archives compress little (ppm about 2:1, jpg not at all); members declaring more than
# this many times the archive's bytes are a zip bomb, not data.
UNPACK_RATIO = 20
UNPACK_SLACK = 16 << 20
FREE_RESERVE = 64 << 20  # never written below: the lock, logs and other programs still need room
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
SHA256 = re.compile(r"[0-9a-f]{64}")
_JSON_KINDS = {bool: "true or false", int: "a number", float: "a number", str: "a string", list: "a list"}


class DownloadError(ValueError):
    """One line: what failed, where, and what to do."""


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
            _record(to, part, digest)
            _place(temporary, target, fetched)
        finally:
            shutil.rmtree(temporary, ignore_errors=True)
    else:
        if not owned:  # a file downloaded by hand is copied into place, leaving the user's own
            dest.parent.mkdir(parents=True, exist_ok=True)
            write_atomically(dest, lambda tmp: shutil.copyfile(fetched, tmp))
        _record(to, part, digest)


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
            if offset == _whole_length(refused):
                os.replace(part, dest)  # the server's own size says the part already holds it all
                return dest
            # A part longer than the file, or a server that does not say the file's size: the part
            # cannot be shown to be the file's beginning, so it is dropped and the file fetched whole.
            part.unlink()
            offset = 0
            response, _ = _open(url, 0, deadline)
        with response:
            start, end, total = _body_range(url, response, offset, part)
            if total is not None and total > cap:
                raise DownloadError(f"{url}: announces {total} bytes, more than the {cap} this file may have "
                                    f"(about {size} expected); nothing was written: check the URL or the mirror")
            if size is None and total is not None:
                deadline.expect(total - start)
            got = _receive(url, response, part, start, end, cap, deadline, console, dest.name)
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
    opener = build_opener(_WatchedHTTP(deadline), _WatchedHTTPS(deadline))
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
        raise DownloadError(f"{url}: cannot connect ({reason}); check the network or pass --from MIRROR_OR_FILE") from None
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
            _shut(sock)

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
                        _shut(sock)
                return


def _shut(sock: socket.socket) -> None:
    try:
        sock.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass  # already closed


def _watched(connection_class, deadline: Deadline):
    class Watched(connection_class):
        def connect(self) -> None:
            super().connect()
            deadline.watch(self.sock)
    return Watched


class _WatchedHTTP(HTTPHandler):
    def __init__(self, deadline: Deadline) -> None:
        super().__init__()
        self.deadline = deadline

    def http_open(self, req):
        return self.do_open(_watched(http.client.HTTPConnection, self.deadline), req)


class _WatchedHTTPS(HTTPSHandler):
    def __init__(self, deadline: Deadline) -> None:
        super().__init__()
        self.deadline = deadline

    def https_open(self, req):
        return self.do_open(_watched(http.client.HTTPSConnection, self.deadline), req, context=self._context)


def _whole_length(error: HTTPError) -> int | None:
    """The file's length from a 416's Content-Range (``bytes */LENGTH``), else None."""
    match = re.fullmatch(r"\s*bytes\s+\*/(\d+)\s*", error.headers.get("Content-Range") or "")
    return int(match.group(1)) if match else None


def _body_range(url: str, response, offset: int, part: Path) -> tuple[int, int | None, int | None]:
    """Where the body starts in the file, where it ends (None: at the connection's end) and
    the file's whole length (None where unknown), checked against what was asked."""
    length = response.headers.get("Content-Length")
    length = int(length) if length is not None and length.strip().isdigit() else None
    if response.status != 206:
        return 0, length, length  # the whole file (a server that ignores ranges starts over)
    content_range = response.headers.get("Content-Range") or ""
    match = re.fullmatch(r"\s*bytes\s+(\d+)-(\d+)/(\d+|\*)\s*", content_range)
    first, last = (int(match.group(1)), int(match.group(2))) if match else (-1, -1)
    total = int(match.group(3)) if match and match.group(3) != "*" else None
    if not match or last < first or (total is not None and last >= total) or \
            (length is not None and length != last - first + 1):
        raise DownloadError(f"{url}: a partial answer (206) with Content-Range {content_range!r} and Content-Length "
                            f"{length}, which do not agree; {part} is kept: rerun, or pass --from another mirror")
    if first != offset and first != 0:
        part.unlink(missing_ok=True)
        raise DownloadError(f"{url}: asked for the bytes from {offset} on, the server sent {first}-{last}; {part} is "
                            "dropped: rerun the same command to fetch the file from the start")
    # first == 0: the server restarted the file; it is written from the start, never appended
    return first, last + 1, total


def _receive(url: str, response, part: Path, start: int, end: int | None, cap: int, deadline: Deadline,
             console: Console | None, label: str) -> int:
    """The body written into `part` from byte `start` on; returns the part's length. Stops at
    `cap`, at the deadline, on a stalled body and at FREE_RESERVE, each with one line; a dropped
    connection ends the loop quietly (the caller compares the length with what was announced)."""
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
                    raise disk_full(part.parent, f"the {got} bytes that arrived in {part.name} are kept and resumed from",
                                    free)
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


def check_free_space(folder: Path, needed: int) -> None:
    free = shutil.disk_usage(folder).free
    if needed > 0 and free < needed + FREE_RESERVE:
        raise DownloadError(f"{folder}: {free / 1e9:.1f} GB free, {(needed + FREE_RESERVE) / 1e9:.1f} GB needed; "
                            "free space or use --to")


def disk_full(folder: Path, kept: str, free: int | None = None) -> DownloadError:
    """The full-disk line of a download: the free space of the filesystem that filled (the
    nearest existing folder of `folder`), and what a rerun finds (`kept`)."""
    where = next((p for p in [folder, *folder.parents] if p.exists()), Path("."))
    try:
        free = shutil.disk_usage(where).free if free is None else free
        room = f" ({free / 2**20:.1f} MiB free there, {FREE_RESERVE >> 20} MiB kept free)"
    except OSError:
        room = ""
    return DownloadError(f"{folder}: no space left on the device{room}; free some space and rerun the same command "
                         f"({kept})")


def read_lock(to: Path) -> dict[str, str]:
    """The hashes recorded by earlier downloads ({file: sha256}), {} where none were; a file
    that is not such a record is one line naming it (never trusted, never overwritten)."""
    path = Path(to) / LOCK_FILE
    if not path.exists():
        return {}
    try:
        record = json.loads(path.read_text())
        problem = "" if isinstance(record, dict) else f"holds {_JSON_KINDS.get(type(record), 'null')}, not files and their hashes"
    except (OSError, UnicodeDecodeError, ValueError) as error:
        record, problem = None, ("empty" if isinstance(error, ValueError) and not path.read_bytes().strip()
                                 else f"not JSON ({str(error).splitlines()[0] if str(error) else type(error).__name__})")
    if not problem:
        bad = next((k for k, v in record.items() if not isinstance(v, str) or not SHA256.fullmatch(v)), None)
        problem = f"the entry {bad!r} is not a sha256" if bad is not None else ""
    if problem:
        raise DownloadError(f"{path}: {problem}, so the hashes of earlier downloads are lost; restore it from a "
                            "backup, or remove it and the next download records them again")
    return record


def _record(to: Path, part: Part, digest: str) -> None:
    """The first complete download's hash, where none is pinned, written atomically."""
    if part.sha256:
        return
    record = read_lock(to)
    if record.get(part.file) == digest:
        return
    record[part.file] = digest
    text = json.dumps(record, indent=1, sort_keys=True) + "\n"
    write_atomically(Path(to) / LOCK_FILE, lambda tmp: tmp.write_text(text))


def verify(path: Path, part: Part, to: Path, owned: bool = True) -> str:
    """The file's sha256 if it is the pinned (or first recorded) one and its md5 the published
    one (where given); else the file is moved aside (`owned`: only a file the download wrote)
    and a one-line error says both hashes. Records nothing (see _record)."""
    sha, md5 = hashlib.sha256(), hashlib.md5() if part.md5 else None
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(CHUNK), b""):
            sha.update(block)
            if md5 is not None:
                md5.update(block)
    digest = sha.hexdigest()
    lock_path = Path(to) / LOCK_FILE
    expected = part.sha256 or read_lock(to).get(part.file)
    checks = [("sha256", digest, expected, "pinned in e3cm-bench" if part.sha256 else
               f"recorded in {lock_path} by the first download")]
    if md5 is not None:
        checks.append(("md5", md5.hexdigest(), part.md5.lower(), "published by the source"))
    for kind, got, want, where in checks:
        if want is not None and got != want:
            raise DownloadError(f"{path.name}: {kind} {got} is not the {want} {where}; {_set_aside(path, owned)}")
    return digest


def _set_aside(path: Path, owned: bool) -> str:
    if not owned:
        return f"{path} is left as it is"
    bad = path.with_name(path.name + ".bad")
    path.replace(bad)
    return f"the file is kept aside as {bad}"


def extract(archive: Path, target: Path, console: Console | None = None) -> Path:
    """Unpack into a temporary folder beside `target`, refusing unsafe members, then rename into
    place (the archive's single top folder, or its contents, become `target`)."""
    temporary = unpack(archive, target, owned=False)
    try:
        _place(temporary, target, archive)
    finally:
        shutil.rmtree(temporary, ignore_errors=True)
    return target


def unpack(archive: Path, target: Path, owned: bool = True) -> Path:
    """The archive unpacked whole into a temporary folder beside `target` (returned): unsafe
    members refused, more than UNPACK_RATIO times the archive's bytes refused, and every member
    read to its end, which checks each zip member's CRC-32 and finds a tar cut short. A damaged
    or refused archive is moved aside (`owned`), so that a rerun fetches it again instead of
    reusing it, and said in one line."""
    temporary = target.with_name(f".{target.name}.extracting")
    shutil.rmtree(temporary, ignore_errors=True)
    temporary.mkdir(parents=True)
    limit = UNPACK_RATIO * archive.stat().st_size + UNPACK_SLACK
    try:
        if zipfile.is_zipfile(archive):
            with zipfile.ZipFile(archive) as zf:
                declared = 0
                for info in zf.infolist():
                    _check_member(info.filename, stat.S_IFMT(info.external_attr >> 16))
                    declared += info.file_size  # a zip member never yields more than it declares
                _check_unpacked_size(declared, limit, temporary)
                zf.extractall(temporary)
        elif tarfile.is_tarfile(archive):
            with tarfile.open(archive) as tf:
                declared = 0
                for member in tf:  # one by one: a bomb is refused at the member that passes the limit
                    kind = stat.S_IFLNK if member.issym() or member.islnk() else \
                        stat.S_IFCHR if not (member.isfile() or member.isdir()) else 0
                    _check_member(member.name, kind)
                    declared += member.size
                    _check_unpacked_size(declared, limit, temporary)
                tf.extractall(temporary, filter="data")
        else:
            raise _Refused("damaged or cut short (neither a zip nor a tar archive)")
    except _Refused as error:
        shutil.rmtree(temporary, ignore_errors=True)
        raise DownloadError(f"{archive}: {error}; no hash was recorded and nothing was extracted; "
                            f"{_set_aside(archive, owned)}: rerun to download it again, or pass --from another mirror") from None
    except (zipfile.BadZipFile, zipfile.LargeZipFile, tarfile.TarError, EOFError, zlib.error, lzma.LZMAError,
            NotImplementedError, OSError) as error:
        shutil.rmtree(temporary, ignore_errors=True)
        if isinstance(error, OSError) and error.errno is not None:
            raise  # the disk or the folder, not the archive (a full disk is said by download)
        why = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise DownloadError(f"{archive}: damaged or cut short ({why}); no hash was recorded and nothing was extracted; "
                            f"{_set_aside(archive, owned)}: rerun the same command to download it again") from None
    except BaseException:
        shutil.rmtree(temporary, ignore_errors=True)
        raise
    return temporary


class _Refused(Exception):
    """An archive that unpack will not unpack (the reason); it becomes a DownloadError there."""


def _check_unpacked_size(declared: int, limit: int, temporary: Path) -> None:
    if declared > limit:
        raise _Refused(f"its members would unpack to at least {declared} bytes, over the {limit} allowed "
                       f"({UNPACK_RATIO} times the archive's size)")
    free = shutil.disk_usage(temporary).free
    if declared + FREE_RESERVE > free:
        raise disk_full(temporary.parent, "the archive is kept", free)


def _place(temporary: Path, target: Path, archive: Path) -> Path:
    """The unpacked archive's single top folder, or its contents, renamed into `target`."""
    top = list(temporary.iterdir())
    content = top[0] if len(top) == 1 and top[0].is_dir() else temporary
    if target.exists():
        shutil.rmtree(target)
    content.rename(target)
    write_atomically(target / ".complete", lambda tmp: tmp.write_text(f"{archive.name}\n"))
    return target


def check(source: Source, to: Path) -> str:
    """What a placed copy holds against what a complete one does: one line, or a DownloadError
    naming what is missing and the command that fetches it."""
    from .benchmarks import get_benchmark

    root = Path(to) / source.folder
    if not root.is_dir():
        raise DownloadError(f"{root}: not found; e3cm-bench download {source.name} --to {to} fetches it")
    try:
        dataset = get_benchmark(source.benchmark).load_dataset(root)
    except ValueError as error:  # the dataset's own words, without the advice meant for a run
        reason = str(error).split(", e.g. ")[0].split("; pass --skip-bad")[0]
        raise DownloadError(f"{source.name} at {root} is incomplete: {reason}") from None
    found = {"pairs": len(dataset)}
    if "sequences" in source.expected:  # an HPatches copy is counted in sequences and images
        sequences = [d for d in root.iterdir() if d.is_dir() and d.name[:2] in ("i_", "v_")]
        found = {"sequences": len(sequences), "images": sum(len(list(d.glob("*.ppm"))) for d in sequences)}
    short = {k: (found.get(k, 0), v) for k, v in source.expected.items() if found.get(k, 0) < v}
    if short:
        counts = ", ".join(f"{k} {got} of {want}" for k, (got, want) in short.items())
        raise DownloadError(f"{source.name} at {root} is incomplete: {counts}")
    return f"{source.name} at {root}: complete (" + ", ".join(f"{v} {k}" for k, v in found.items()) + ")"


def find_root(benchmark: str, root: Path | None) -> Path:
    """--root as given, else the benchmark's data under data_dir() in the first of its layouts
    that is there and complete (else a one-line error names the download command that fixes it)."""
    from .datasets.sources import data_dir, default_sources

    if root is not None:
        return Path(root)
    sources = default_sources(benchmark)
    errors = []
    for source in sources:
        try:
            check(source, data_dir())
            return data_dir() / source.folder
        except DownloadError as error:
            errors.append(error)
    fixes = " or ".join(f"e3cm-bench download {s.name} --to {data_dir()}" for s in sources)
    problem = str(errors[0]).split("; e3cm-bench download")[0]
    raise DownloadError(f"no --root given and {problem}; {fixes} fetches it (or pass --root)")


def status(source: Source, to: Path) -> str:
    """One line for `e3cm-bench datasets`: where a source's data is looked for and what is there."""
    root = Path(to) / source.folder
    recorded = read_lock(to)  # a damaged record is one line, whatever the copies hold
    try:
        line = check(source, to)
    except DownloadError as error:
        text = str(error)
        return f"{source.name}: {'missing' if 'not found' in text else 'incomplete'} at {root} ({text.split(': ', 1)[-1]})"
    hashes = [part.file for part in source.parts if part.file in recorded]
    return line + (f"; sha256 recorded for {', '.join(hashes)}" if hashes else "; no download recorded (placed by hand)")


def _check_member(name: str, kind: int) -> None:
    path = PurePosixPath(name.replace("\\", "/"))
    if path.is_absolute() or ".." in path.parts or (len(name) > 1 and name[1] == ":"):
        raise _Refused(f"member {name!r} would be written outside the folder")
    if kind in (stat.S_IFLNK, stat.S_IFCHR, stat.S_IFBLK, stat.S_IFIFO, stat.S_IFSOCK):
        raise _Refused(f"member {name!r} is a link or a device file")


def _progress(console: Console | None) -> Progress:
    return Progress(TextColumn("[bold]{task.description}"), BarColumn(), DownloadColumn(), TransferSpeedColumn(),
                    TextColumn("ETA"), TimeRemainingColumn(), console=console or Console())

