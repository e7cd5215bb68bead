"""A data folder: the hashes recorded by its downloads (LOCK_FILE), a file verified against them,
its free space, and whether a source's copy in it is complete (`check`, `find_root`, `status`).
download.py fetches into it; archives.py unpacks into it."""

from __future__ import annotations

import hashlib
import json
import re
import shutil
from pathlib import Path

from e3cm_bench.datasets.sources import Part, Source
from e3cm_bench.ground.files import write_atomically

CHUNK = 1 << 20
FREE_RESERVE = 64 << 20  # never written below: the lock, logs and other programs still need room
LOCK_FILE = "e3cm-bench-data.lock"
SHA256 = re.compile(r"[0-9a-f]{64}")
_JSON_KINDS = {bool: "true or false", int: "a number", float: "a number", str: "a string", list: "a list"}


class DownloadError(ValueError):
    """One line: what failed, where, and what to do."""


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
        problem = (
            ""
            if isinstance(record, dict)
            else f"holds {_JSON_KINDS.get(type(record), 'null')}, not files and their hashes"
        )
    except (OSError, UnicodeDecodeError, ValueError) as error:
        record, problem = (
            None,
            (
                "empty"
                if isinstance(error, ValueError) and not path.read_bytes().strip()
                else f"not JSON ({str(error).splitlines()[0] if str(error) else type(error).__name__})"
            ),
        )
    if not problem:
        bad = next((k for k, v in record.items() if not isinstance(v, str) or not SHA256.fullmatch(v)), None)
        problem = f"the entry {bad!r} is not a sha256" if bad is not None else ""
    if problem:
        raise DownloadError(f"{path}: {problem}, so the hashes of earlier downloads are lost; restore it from a "
                            "backup, or remove it and the next download records them again")
    return record


def record_hash(to: Path, part: Part, digest: str) -> None:
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
    and a one-line error says both hashes. Records nothing (see record_hash)."""
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
            raise DownloadError(f"{path.name}: {kind} {got} is not the {want} {where}; {set_aside(path, owned)}")
    return digest


def set_aside(path: Path, owned: bool) -> str:
    if not owned:
        return f"{path} is left as it is"
    bad = path.with_name(path.name + ".bad")
    path.replace(bad)
    return f"the file is kept aside as {bad}"


def check(source: Source, to: Path) -> str:
    """What a placed copy holds against what a complete one does: one line, or a DownloadError
    naming what is missing and the command that fetches it."""
    from e3cm_bench.benchmarks import get_benchmark

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
    from e3cm_bench.datasets.sources import data_dir, default_sources

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
        return (
            f"{source.name}: {'missing' if 'not found' in text else 'incomplete'} at {root} ({text.split(': ', 1)[-1]})"
        )
    hashes = [part.file for part in source.parts if part.file in recorded]
    return line + (
        f"; sha256 recorded for {', '.join(hashes)}" if hashes else "; no download recorded (placed by hand)"
    )
