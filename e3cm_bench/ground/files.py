"""Reading and writing the files of a run: atomic writes, YAML, CSV, hashes, versions, environment.

Every file is written through `write_atomically` (an interrupted write leaves the old file or the
new one); every reader turns a broken file into a one-line ValueError that names the file."""

from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import os
import platform
import socket
import stat
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from importlib import metadata
from pathlib import Path

import pandas as pd
import yaml

PACKAGES = tuple("e3cm-bench torch torchvision numpy opencv-python-headless h5py pandas poselib pycolmap".split())
# Variables that choose the CPU kernels (oneDNN, ATen), and the CPU flags the defaults pick them by.
ISA_VARIABLES = ("ONEDNN_MAX_CPU_ISA", "ATEN_CPU_CAPABILITY")
CPU_FLAGS = ("avx512_bf16", "amx_bf16", "avx512f", "avx2")
# The flags of those with which a CPU computes bf16 natively (oneDNN's bf16 kernels need one).
BF16_FLAGS = ("avx512_bf16", "amx_bf16")
CSV_FLOAT_FORMAT = "%.8g"


def package_versions() -> dict[str, str]:
    versions = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return versions


def cpu_info() -> tuple[str | None, set[str] | None]:
    """The CPU's model name and flags from /proc/cpuinfo (first processor); (None, None) where absent."""
    try:
        text = Path("/proc/cpuinfo").read_text(errors="replace")
    except OSError:
        return None, None
    model, flags = None, None
    for line in text.splitlines():
        key, _, value = line.partition(":")
        key = key.strip()
        if model is None and key in ("model name", "Processor", "cpu model"):
            model = value.strip() or None
        elif flags is None and key in ("flags", "Features"):
            flags = set(value.split())
        if model is not None and flags is not None:
            break
    return model, flags


def cpu_isa() -> str:
    """The CPU's instruction sets that decide its speed here, as "avx512_bf16+avx512f+avx2"
    ("unknown" where /proc/cpuinfo is absent): what the speed tables print beside each figure."""
    _, flags = cpu_info()
    return "+".join(f for f in CPU_FLAGS if f in (flags or ())) or "unknown"


def run_environment() -> dict:
    """What a run's numbers depend on beyond package versions (config.yaml's ``environment``).

    torch's version string with its build tag, the CPU capability torch dispatches to
    (``torch.backends.cpu.get_cpu_capability()``: AVX512, AVX2, DEFAULT ...), the environment
    variables that change it (recorded only when set), torch's thread count, the CPU model and
    whether it has each of CPU_FLAGS (null where /proc/cpuinfo is absent).
    oneDNN picks other convolution kernels on other instruction sets, and those round differently.
    """
    import torch  # lazily: files.py is imported by commands that never need torch

    capability = str(torch.backends.cpu.get_cpu_capability())
    model, flags = cpu_info()
    # torch's own version string names its build (2.14.1+cu130, 2.14.1+cpu), which the
    # package metadata in `versions` may not.
    environment = {"torch": str(torch.__version__), "cpu_capability": capability}
    environment.update({name: os.environ[name] for name in ISA_VARIABLES if os.environ.get(name)})
    environment["threads"] = int(torch.get_num_threads())
    environment["cpu_model"] = model or platform.processor() or platform.machine() or "unknown"
    environment["cpu_flags"] = None if flags is None else {flag: flag in flags for flag in CPU_FLAGS}
    return environment


def file_sha256(path: str | Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def refuse_link(path: str | Path) -> Path:
    """`path`, or a one-line ValueError where it is a symbolic link (dangling or not).

    The toolkit never writes through a link: a link planted in an output folder (``.lock ->
    ~/notes.txt``) would otherwise have its target truncated or created. Where a file is
    replaced by a rename the link is never followed anyway; refusing says so instead of
    silently dropping a link the user may have made on purpose."""
    path = Path(path)
    if path.is_symlink():
        raise ValueError(f"{path}: is a symbolic link (to {os.readlink(path)}); e3cm-bench does not write through "
                         "links: remove it or choose another --out")
    return path


# O_NOFOLLOW: a link at the name is an error (ELOOP), never followed; O_EXCL: a file that is
# already there (a link included) is an error, never reused; O_CLOEXEC: not inherited.
NEW_FILE_FLAGS = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC


def create_new(path: str | Path, mode: int = 0o666):
    """A new file at `path` opened for binary writing, created with NEW_FILE_FLAGS (whatever
    is at the name, a link above all, is refused in one line naming it)."""
    path = Path(path)
    try:
        fd = os.open(path, NEW_FILE_FLAGS, mode)
    except FileExistsError:
        refuse_link(path)
        raise ValueError(f"{path}: already exists; e3cm-bench writes only files it creates") from None
    return os.fdopen(fd, "wb")


def write_atomically(path: str | Path, write: Callable[[Path], None]) -> Path:
    """Write through a temporary file in the same folder, then rename over ``path``.

    The rename is atomic on one filesystem, and replaces a name without following it. The
    temporary file is created 0600 by mkstemp (O_CREAT | O_EXCL: never an existing file or
    link); the result gets the mode a plain ``open`` would have given (umask honoured). A
    symbolic link at ``path`` is refused (refuse_link).
    """
    path = refuse_link(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp_name)
    try:
        write(tmp_path)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp_path, 0o666 & ~umask)
        os.replace(tmp_path, path)
    finally:
        tmp_path.unlink(missing_ok=True)
    return path


def save_npz(path: str | Path, **arrays) -> Path:
    """`np.savez` through write_atomically (given a name, np.savez would open it following a link,
    and add '.npz' to a temporary's name)."""
    import numpy as np

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)

    return write_atomically(path, write)


def yaml_plain(value):
    """YAML-safe plain Python values (paths, tuples, numpy scalars)."""
    if isinstance(value, dict):
        return {str(k): yaml_plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [yaml_plain(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if hasattr(value, "item") and not isinstance(value, (str, bytes)):
        return value.item()
    return value


def absolute_paths(value):
    """Paths (alone or in a list) as absolute strings; other values as they are."""
    if isinstance(value, Path):
        return str(value.resolve())
    if isinstance(value, (list, tuple)):
        return [absolute_paths(v) for v in value]
    return value


def save_yaml(data: dict, path: str | Path) -> Path:
    text = yaml.safe_dump(yaml_plain(data), sort_keys=False)
    return write_atomically(path, lambda tmp: tmp.write_text(text))


MAX_YAML_BYTES = 1 << 20  # a config of this toolkit is a few KiB
MAX_YAML_DEPTH = 32       # nesting levels; its configs use four


class YamlRefused(yaml.YAMLError):
    """A YAML document this toolkit will not read (aliases, too deep); the message says why."""


class _BoundedLoader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing aliases (an alias bomb expands a few KiB into gigabytes)
    and nesting deeper than MAX_YAML_DEPTH (deep nesting exhausts the recursion limit)."""

    _depth = 0

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            mark = self.peek_event().start_mark
            raise YamlRefused(f"aliases (*name) are not accepted (line {mark.line + 1}); write the values out")
        self._depth += 1
        try:
            if self._depth > MAX_YAML_DEPTH:
                mark = self.peek_event().start_mark
                raise YamlRefused(f"nested deeper than {MAX_YAML_DEPTH} levels (line {mark.line + 1})")
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


def safe_yaml(text: str):
    """One YAML document read with the bounded safe loader (YAMLError when refused or broken)."""
    if len(text) > MAX_YAML_BYTES:
        raise YamlRefused(f"{len(text)} bytes, over the {MAX_YAML_BYTES} a config may hold")
    return yaml.load(text, Loader=_BoundedLoader)  # noqa: S506 - a SafeLoader subclass


def load_yaml_text(text: str):
    """One YAML value from a command-line string ('4' -> 4, 'false' -> False, 'own' -> 'own')."""
    try:
        return safe_yaml(text)
    except YamlRefused:
        raise ValueError(f"--set value {text[:40]!r}: not accepted") from None
    except (yaml.YAMLError, RecursionError):
        return text


def load_yaml(path: str | Path, what: str = "YAML file") -> dict:
    """A YAML mapping; ValueError naming the file when it is missing, too large, broken,
    refused (aliases, deep nesting) or not a mapping."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: {what} not found")
    try:
        size = path.stat().st_size
        if size > MAX_YAML_BYTES:
            raise ValueError(f"{path}: {size} bytes, over the {MAX_YAML_BYTES} a {what} may hold")
        data = safe_yaml(path.read_text())
    except YamlRefused as exc:
        raise ValueError(f"{path}: {exc}") from None
    except (OSError, UnicodeDecodeError, yaml.YAMLError, RecursionError) as exc:
        first_line = (str(exc).splitlines() or [type(exc).__name__])[0]
        raise ValueError(f"{path}: not valid YAML ({first_line})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping at the top level, got {type(data).__name__}")
    return data


def write_csv(df: pd.DataFrame, path: str | Path) -> Path:
    """Write ``df`` without its index, floats as ``%.8g`` (inf stays ``inf``), atomically."""
    return write_atomically(path, lambda tmp: df.to_csv(tmp, index=False, float_format=CSV_FLOAT_FORMAT))


def read_csv(path: str | Path, what: str = "CSV file") -> pd.DataFrame:
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: {what} missing")
    try:
        return pd.read_csv(path)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not a readable CSV ({type(exc).__name__})") from None


def read_keyed_csv(path: str | Path, what: str, keys: Sequence[str], unique: bool = True) -> pd.DataFrame:
    """A CSV whose rows are named by `keys`: a one-line ValueError naming the file for a
    missing key column and (unique) for a key that has more than one row, since the last of
    them would silently win wherever the rows are looked up."""
    path = Path(path)
    table = read_csv(path, what=what)
    missing = [c for c in keys if c not in table.columns]
    if missing:
        raise ValueError(f"{path}: missing column(s) {', '.join(missing)}")
    repeated = table.duplicated(list(keys)) if unique else pd.Series(False, index=table.index)
    if repeated.any():
        first = int(repeated.to_numpy().nonzero()[0][0])
        named = ", ".join(f"{k} {table.iloc[first][k]}" for k in keys)
        raise ValueError(f"{path}: {named} has more than one row (line {first + 2})")
    return table


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
