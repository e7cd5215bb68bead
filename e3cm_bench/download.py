"""`e3cm-bench download`: fetch a benchmark's files (resuming), verify them, unpack them safely.

- Fetching resumes: bytes arrive in ``FILE.part``; a rerun asks the server for the rest
  (an HTTP range request) and starts over only where the server refuses ranges.
- Verifying: sha256 against the hash pinned in datasets/sources.py; where none is pinned,
  against the hash recorded in LOCK_FILE beside the data by the first download (which
  records it). A file that does not match is moved aside to ``FILE.bad``, never used.
- Unpacking: into a temporary folder beside the target, renamed into place at the end;
  members with absolute paths, ``..``, links or device files are refused (tar: Python's
  ``data`` filter; zip: checked here), nothing is written outside the target.
- Before fetching, the free disk is checked against the file's size (twice for archives).
"""

from __future__ import annotations

import http.client
import json
import shutil
import stat
import tarfile
import zipfile
from pathlib import Path, PurePosixPath
from urllib.error import HTTPError, URLError
from urllib.request import Request, urlopen

from rich.console import Console
from rich.progress import BarColumn, DownloadColumn, Progress, TextColumn, TimeRemainingColumn, TransferSpeedColumn

from .datasets.sources import Part, Source
from .files import file_sha256

LOCK_FILE = "e3cm-bench-data.lock"
CHUNK = 1 << 20
TIMEOUT_S = 60


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
        parts = (Part(parts[0].file, origin, sha256 or parts[0].sha256, parts[0].size, parts[0].extract),)
    elif sha256 is not None:
        raise DownloadError("--sha256 goes with --from (the hash of the file given there)")
    to.mkdir(parents=True, exist_ok=True)
    for part in parts:
        if part.url is None:
            continue
        archive = to / ".downloads" / Path(part.file).name if part.extract else target / part.file
        if not (part.extract and (target.exists() and (target / ".complete").exists())):
            fetched = fetch(part.url, archive, part.size, part.extract, console)
            verify(fetched, part, to)
            if part.extract:
                extract(fetched, target, console)
    if source.manual:
        raise DownloadError(f"{source.name}: {source.manual.format(folder=target)}; then check it with "
                            f"e3cm-bench download {source.name} --to {to} --check")
    return target


def fetch(url: str, dest: Path, size: int | None = None, archive: bool = False, console: Console | None = None) -> Path:
    """dest, downloaded from `url` (or a local file's path / file:// URL, used as it is)."""
    local = Path(url[len("file://"):]) if url.startswith("file://") else Path(url)
    if "://" not in url or url.startswith("file://"):
        if not local.is_file():
            raise DownloadError(f"{local}: no such file")
        return local
    if dest.is_file():
        return dest
    dest.parent.mkdir(parents=True, exist_ok=True)
    part = dest.with_name(dest.name + ".part")
    offset = part.stat().st_size if part.exists() else 0
    check_free_space(dest.parent, (size or 0) * (2 if archive else 1) - offset)
    request = Request(url, headers={"Range": f"bytes={offset}-"} if offset else {})
    try:
        response = urlopen(request, timeout=TIMEOUT_S)  # noqa: S310 - the URLs come from sources.py or --from
    except HTTPError as error:
        if error.code == 416 and offset:  # nothing left to send: the part is whole
            part.rename(dest)
            return dest
        raise DownloadError(f"{url}: HTTP {error.code} {error.reason}") from None
    except (URLError, OSError) as error:
        reason = getattr(error, "reason", error)
        raise DownloadError(f"{url}: cannot connect ({reason}); check the network or pass --from MIRROR_OR_FILE") from None
    with response:
        resumed = offset > 0 and response.status == 206
        if not resumed:
            offset = 0  # the server sends the whole file: start over
        length = response.headers.get("Content-Length")
        total = offset + int(length) if length is not None else None
        if total is not None:
            check_free_space(dest.parent, (total - offset) * (2 if archive else 1))
        with open(part, "ab" if resumed else "wb") as out, _progress(console) as progress:
            task = progress.add_task(dest.name, total=total, completed=offset)
            try:
                while chunk := response.read(CHUNK):
                    out.write(chunk)
                    progress.advance(task, len(chunk))
            except (OSError, http.client.HTTPException):
                pass  # the connection dropped: what arrived is kept, and the size check below says so
    got = part.stat().st_size
    if total is not None and got != total:
        raise DownloadError(f"{url}: the connection dropped at {got} of {total} bytes; {part} is kept, "
                            "rerun the same command to resume")
    part.rename(dest)
    return dest


def check_free_space(folder: Path, needed: int) -> None:
    free = shutil.disk_usage(folder).free
    if needed > 0 and free < needed:
        raise DownloadError(f"{folder}: {free / 1e9:.1f} GB free, {needed / 1e9:.1f} GB needed; free space or use --to")


def verify(path: Path, part: Part, to: Path) -> str:
    """The file's sha256 if it is the pinned (or first recorded) one; else the file is moved
    aside and a one-line error says both hashes."""
    digest = file_sha256(path)
    lock_path = to / LOCK_FILE
    lock = json.loads(lock_path.read_text()) if lock_path.is_file() else {}
    expected = part.sha256 or lock.get(part.file)
    if expected is not None and digest != expected:
        bad = path.with_name(path.name + ".bad")
        path.replace(bad)
        where = "pinned in e3cm-bench" if part.sha256 else f"recorded in {lock_path} by the first download"
        raise DownloadError(f"{path.name}: sha256 {digest} is not the {expected} {where}; the file is kept aside as {bad}")
    if expected is None:
        lock[part.file] = digest
        lock_path.write_text(json.dumps(lock, indent=1, sort_keys=True) + "\n")
    return digest


def extract(archive: Path, target: Path, console: Console | None = None) -> Path:
    """Unpack into a temporary folder beside `target`, refusing unsafe members, then rename into
    place (the archive's single top folder, or its contents, become `target`)."""
    temporary = target.with_name(f".{target.name}.extracting")
    shutil.rmtree(temporary, ignore_errors=True)
    temporary.mkdir(parents=True)
    try:
        if zipfile.is_zipfile(archive):
            with zipfile.ZipFile(archive) as zf:
                for info in zf.infolist():
                    _check_member(archive, info.filename, stat.S_IFMT(info.external_attr >> 16))
                zf.extractall(temporary)
        elif tarfile.is_tarfile(archive):
            with tarfile.open(archive) as tf:
                for member in tf.getmembers():
                    kind = stat.S_IFLNK if member.issym() or member.islnk() else \
                        stat.S_IFCHR if not (member.isfile() or member.isdir()) else 0
                    _check_member(archive, member.name, kind)
                tf.extractall(temporary, filter="data")
        else:
            raise DownloadError(f"{archive}: neither a zip nor a tar archive")
        top = [p for p in temporary.iterdir()]
        content = top[0] if len(top) == 1 and top[0].is_dir() else temporary
        if target.exists():
            shutil.rmtree(target)
        content.rename(target)
        (target / ".complete").write_text(f"{archive.name}\n")
    finally:
        shutil.rmtree(temporary, ignore_errors=True)
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
    lock = Path(to) / LOCK_FILE
    try:
        line = check(source, to)
    except DownloadError as error:
        text = str(error)
        return f"{source.name}: {'missing' if 'not found' in text else 'incomplete'} at {root} ({text.split(': ', 1)[-1]})"
    recorded = json.loads(lock.read_text()) if lock.is_file() else {}
    hashes = [part.file for part in source.parts if part.file in recorded]
    return line + (f"; sha256 recorded for {', '.join(hashes)}" if hashes else "; no download recorded (placed by hand)")


def _check_member(archive: Path, name: str, kind: int) -> None:
    path = PurePosixPath(name.replace("\\", "/"))
    if path.is_absolute() or ".." in path.parts or (len(name) > 1 and name[1] == ":"):
        raise DownloadError(f"{archive}: member {name!r} would be written outside the folder; nothing was extracted")
    if kind in (stat.S_IFLNK, stat.S_IFCHR, stat.S_IFBLK, stat.S_IFIFO, stat.S_IFSOCK):
        raise DownloadError(f"{archive}: member {name!r} is a link or a device file; nothing was extracted")


def _progress(console: Console | None) -> Progress:
    return Progress(TextColumn("[bold]{task.description}"), BarColumn(), DownloadColumn(), TransferSpeedColumn(),
                    TextColumn("ETA"), TimeRemainingColumn(), console=console or Console())

