"""Reading and writing the files of a run: atomic writes, YAML, CSV, hashes. (The machine a result
was made on is ground/machine.py's; a run folder's lock, ground/locks.py's.)

Every file is written through `write_atomically` (an interrupted write leaves the old file or the
new one); every reader turns a broken file into a one-line ValueError that names the file."""

from __future__ import annotations

import hashlib
import os
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path

import pandas as pd
import yaml

CSV_FLOAT_FORMAT = "%.8g"


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




def __getattr__(name: str):
    from e3cm_bench.ground.moved import moved_name

    return moved_name(__name__, name)  # a name moved to another module (ground/moved.py MOVED_NAMES)
