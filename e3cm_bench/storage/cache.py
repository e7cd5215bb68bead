"""An HDF5 store of matches, one group per image pair, that survives interrupted runs and damage.

A pair name such as ``"v_graffiti/1-2"`` becomes the nested group ``v_graffiti/1-2``
holding the datasets ``keypoints0``, ``keypoints1`` (N x 2 float32) and ``scores``
(N float32), plus the caller's attributes (image sizes, timings).

Crash safety: a block file on disk is never opened for writing. A write reads the block
into memory, adds the pair there (HDF5 on an in-memory file), writes the result to a
temporary file beside it with plain Python I/O, flushes it to disk and renames it over the
block (an atomic replace). A full disk, a signal or a crash at any point leaves the old
block whole, every earlier pair readable; a full disk is an OSError (ENOSPC) that the
caller turns into one line, never an HDF5 library failure. The space a write needs is
checked first (DiskFullError): the temporary copy of the block with the pair added (the old
block is already counted as used, and the rename frees it), WRITE_MARGIN_BYTES beyond. The attribute
``complete=1`` is still set last, and the pairs are spread over block files of at most
BLOCK_PAIRS pairs (``matches.h5``, ``matches.001.h5``, ...), so that a block damaged by
other means (a copy cut short) costs at most its own pairs: ``names`` lists the file in
``damaged`` (no pair is ever written into it again) and keeps only the pairs HDF5 can still
read whole from it; the run matches the others again. A block whose end was cut is read
with the missing bytes taken as zeros up to the length its superblock records (HDF5 refuses
to open a file shorter than that), which keeps every pair whose metadata and compressed
data lie before the cut; a pair whose data was lost fails to decompress and is left out.

A block is a file from outside as much as ours: before a pair's arrays are read, their
declared shapes are checked (N x 2, N x 2 and N, with N at most MAX_PAIR_MATCHES), so that a
small file declaring gigabytes is one line naming the file and the pair, never an allocation.
"""

from __future__ import annotations

import errno
import io
import os
import re
import shutil
from pathlib import Path

import h5py
import numpy as np

from e3cm_bench.ground.files import create_new, refuse_link
from e3cm_bench.ground.matches import Matches

DATASETS = ("keypoints0", "keypoints1", "scores")
COMPLETE_ATTR = "complete"
BLOCK_PAIRS = 50  # pairs per file: the most a damaged file can cost
SPARE_BYTES = 256 << 10  # kept free beyond what a write needs (config.yaml and the like)
# Beyond the block's bytes and the pair's arrays, a write adds the pair's HDF5 metadata (its
# group, three dataset headers, the attributes: a few KiB) and, at worst, gzip's growth of data
# it cannot compress (a few bytes per block); 64 KiB and 1/64 of the arrays cover both.
WRITE_MARGIN_BYTES = 64 << 10
# Matches of one pair a block may declare: 10 million (about 200 MB of arrays) is ten times what
# a dense matcher at full resolution returns; a declared size beyond it is damage or a hostile file.
MAX_PAIR_MATCHES = 10_000_000
# A cut block is read only when what is left is at least this fraction of its recorded length
# (the zeros standing for the lost tail are held in memory).
MIN_RECOVERABLE_FRACTION = 0.5


class DiskFullError(OSError):
    """Not enough free space for the next write; one line naming the folder and the space."""

    def __init__(self, folder: Path, need: int, free: int, what: str = "the next write") -> None:
        super().__init__(errno.ENOSPC, f"{folder}: not enough free disk space ({_size(free)} free, about {_size(need)} "
                                       f"needed for {what}); free some space and rerun the same command: "
                                       "every pair already written resumes")


def _size(n: int) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} GiB"


def check_free_space(folder: Path, need: int, what: str = "the next write") -> None:
    """DiskFullError unless `folder`'s filesystem has `need` bytes (plus SPARE_BYTES) free;
    `what` names what the bytes are for in its message."""
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return
    if free < need + SPARE_BYTES:
        raise DiskFullError(folder, need + SPARE_BYTES, free, what)


class MatchCache:
    """Matches of many image pairs in block files of at most BLOCK_PAIRS pairs, keyed by pair name.

    ``path`` is the first block (``matches.h5``); later blocks sit beside it.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.damaged: list[Path] = []  # blocks found unreadable by the last names()
        self.recovered: dict[Path, int] = {}  # damaged block -> pairs still read whole from it
        self._where: dict[str, Path] | None = None  # pair -> block, from the last names()
        self._counts: dict[Path, int] = {}

    def blocks(self) -> list[Path]:
        """The block files that exist, in order."""
        return [path for _, path in self._indexed_blocks()]

    def clear(self) -> None:
        """Delete every block file (a run started over with --overwrite)."""
        for block in self.blocks():
            block.unlink()
        self._where, self._counts, self.damaged, self.recovered = None, {}, [], {}

    def _indexed_blocks(self) -> list[tuple[int, Path]]:
        pattern = re.compile(re.escape(self.path.stem) + r"\.(\d{3,})" + re.escape(self.path.suffix) + "$")
        later = sorted((int(m.group(1)), p) for p in self.path.parent.glob(f"{self.path.stem}.*{self.path.suffix}")
                       if (m := pattern.match(p.name)))
        return ([(0, self.path)] if self.path.exists() else []) + later

    def _block(self, index: int) -> Path:
        return self.path if index == 0 else self.path.with_name(f"{self.path.stem}.{index:03d}{self.path.suffix}")

    # ------------------------------------------------------------------ queries

    def names(self) -> list[str]:
        """The names of all complete entries in readable blocks, sorted; unreadable blocks go to ``damaged``."""
        self._where, self._counts, self.damaged, self.recovered = {}, {}, [], {}
        recovered: dict[str, Path] = {}
        for block in self.blocks():
            found: list[str] = []
            try:
                with _open(block, "r") as file:

                    def collect(key: str, item: h5py.HLObject) -> None:
                        if _is_complete(item):
                            found.append(key)

                    file.visititems(collect)
            except (OSError, ValueError, RuntimeError, KeyError):
                self.damaged.append(block)
                readable = _readable_pairs(block)
                self.recovered[block] = len(readable)
                for name in readable:
                    recovered.setdefault(name, block)
                continue
            self._counts[block] = len(found)
            for name in found:
                self._where.setdefault(name, block)
        for name, block in recovered.items():  # a pair written whole since, in a later block, wins
            self._where.setdefault(name, block)
        return sorted(self._where)

    def read(self, name: str) -> Matches:
        """The stored matches; ``info`` holds the attributes given to ``write``."""
        key = _group_key(name)
        if self._where is None or name not in self._where:
            self.names()
        block = self._where.get(name)
        if block is None:
            raise KeyError(f"pair {name!r} has no complete entry in {self.path}")
        with _open_for_reading(block, block in self.damaged) as file:
            group = file.get(key)
            if not _is_complete(group):
                raise KeyError(f"pair {name!r} has no complete entry in {block}")
            return _read_entry(group, block, name)

    # ---------------------------------------------------------------- mutations

    def write(self, name: str, matches: Matches, attrs: dict | None = None) -> None:
        """Store the matches of one pair, replacing any earlier (or half-written) entry.

        ``attrs`` values must be numbers, strings, booleans or arrays/sequences of them
        (what HDF5 attributes hold). ``matches.info`` is not stored: it is free-form
        diagnostics, while the attributes are what later stages need.
        """
        key = _group_key(name)
        attrs = dict(attrs or {})
        if COMPLETE_ATTR in attrs:
            raise ValueError(f"attribute name {COMPLETE_ATTR!r} is reserved by the match cache")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        block = self._block_for(name)
        old = block.read_bytes() if block.exists() else b""
        payload = sum(np.asarray(v).nbytes for v in (matches.keypoints0, matches.keypoints1, matches.scores))
        check_free_space(block.parent, len(old) + payload + payload // 64 + WRITE_MARGIN_BYTES)
        buffer = io.BytesIO(old)
        try:
            file = h5py.File(buffer, "a")
        except OSError:
            raise ValueError(_not_hdf5_message(block)) from None
        with file:
            group = file.require_group(key)
            # Clear only this entry's own content: a group may also be the parent of
            # other pairs' groups (a name that prefixes another), which must survive.
            _clear_entry(group)
            for dataset, values in zip(DATASETS, (matches.keypoints0, matches.keypoints1, matches.scores)):
                group.create_dataset(dataset, data=values, compression="gzip", compression_opts=4)
            for attr, value in attrs.items():
                try:
                    group.attrs[attr] = value
                except (TypeError, ValueError) as error:
                    raise TypeError(
                        f"attribute {attr!r}={value!r} cannot be stored in HDF5 ({error})"
                    ) from error
            group.attrs[COMPLETE_ATTR] = 1  # last, so an entry is never complete half-written
        _replace(block, buffer.getbuffer())
        if name not in self._where:
            self._counts[block] = self._counts.get(block, 0) + 1
        self._where[name] = block

    def _block_for(self, name: str) -> Path:
        """The block a pair is written to: its own when rewritten, else the last block with room
        (never a damaged one: a new block follows it)."""
        if self._where is None:
            self.names()
        if name in self._where and self._where[name] not in self.damaged:
            return self._where[name]
        existing = self._indexed_blocks()
        if existing:
            index, last = existing[-1]
            if last not in self.damaged and self._counts.get(last, 0) < BLOCK_PAIRS:
                return last
            return self._block(index + 1)
        return self.path

def _replace(path: Path, data) -> None:
    """`data` becomes the content of `path` all at once: written beside it, flushed, renamed over it."""
    temporary = path.with_name(f".{path.name}.writing")
    refuse_link(path)
    # A stale temporary (a killed run's) is removed, and the new one is created with O_EXCL |
    # O_NOFOLLOW, so neither name is ever written through a link.
    temporary.unlink(missing_ok=True)
    try:
        with create_new(temporary) as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def _open(path: Path, mode: str) -> h5py.File:
    # h5py reports a foreign file as a bare OSError; say which file and what to do.
    if path.exists() and not h5py.is_hdf5(path):
        raise ValueError(_not_hdf5_message(path))
    try:
        return h5py.File(path, mode)
    except OSError as error:
        if "signature" in str(error).lower() or "truncated" in str(error).lower():
            raise ValueError(_not_hdf5_message(path)) from error
        raise


def _read_entry(group: h5py.Group, block: Path, name: str) -> Matches:
    """One pair's matches, its arrays' declared shapes checked before any is read."""
    shapes = {}
    for dataset in DATASETS:
        item = group.get(dataset)
        if not isinstance(item, h5py.Dataset):
            raise ValueError(f"{block}: pair {name}: {dataset} is missing (delete the file or rerun with --overwrite)")
        shapes[dataset] = item.shape
    n = shapes["scores"][0] if len(shapes["scores"]) == 1 else -1
    expected = {"keypoints0": (n, 2), "keypoints1": (n, 2), "scores": (n,)}
    if n < 0 or n > MAX_PAIR_MATCHES or any(shapes[d] != expected[d] for d in DATASETS):
        declared = ", ".join(f"{d} {'x'.join(map(str, shapes[d])) or 'scalar'}" for d in DATASETS)
        raise ValueError(
            f"{block}: pair {name}: the file declares {declared}; expected N x 2, N x 2 and N with N at most "
            f"{MAX_PAIR_MATCHES:,} (a damaged or foreign file: delete it or rerun with --overwrite)"
        )
    info = {k: _plain(v) for k, v in group.attrs.items() if k != COMPLETE_ATTR}
    return Matches(keypoints0=group["keypoints0"][()], keypoints1=group["keypoints1"][()],
                   scores=group["scores"][()], info=info)


def _open_for_reading(block: Path, damaged: bool) -> h5py.File:
    """A block to read pairs from; one cut short (known as damaged, or cut since it was listed)
    is read as _open_cut reads it."""
    if not damaged:
        try:
            return _open(block, "r")
        except ValueError:
            pass
    return _open_cut(block)


def _open_cut(path: Path) -> h5py.File:
    """A block whose end is missing, opened read-only in memory with the lost bytes as zeros up
    to the length its superblock records; ValueError when it is not such a block."""
    data = path.read_bytes()
    try:
        return h5py.File(io.BytesIO(data), "r")
    except OSError as error:
        recorded = re.search(r"stored_eof = (\d+)", str(error))
    if recorded is None:
        raise ValueError(_not_hdf5_message(path))
    length = int(recorded.group(1))
    if not len(data) < length <= len(data) / MIN_RECOVERABLE_FRACTION:
        raise ValueError(_not_hdf5_message(path))
    try:
        return h5py.File(io.BytesIO(data + bytes(length - len(data))), "r")
    except OSError:
        raise ValueError(_not_hdf5_message(path)) from None


def _readable_pairs(block: Path) -> list[str]:
    """The complete pairs of a damaged block that read back whole (arrays decompressed, shapes
    and values sound); none when the block cannot be opened even as a cut one."""
    try:
        file = _open_cut(block)
    except (OSError, ValueError):
        return []
    found: list[str] = []

    def walk(group: h5py.Group, prefix: str) -> None:
        # Not visititems: HDF5's visit stops at the first object it cannot decode, losing the
        # readable pairs after it; each link is tried on its own here.
        try:
            keys = list(group.keys())
        except (OSError, RuntimeError, KeyError, ValueError):
            return
        for key in keys:
            name = f"{prefix}{key}"
            try:
                item = group[key]
            except (OSError, RuntimeError, KeyError, ValueError):
                continue
            if not isinstance(item, h5py.Group):
                continue
            try:
                if _is_complete(item):
                    _read_entry(item, block, name)
                    found.append(name)
            except (OSError, RuntimeError, KeyError, ValueError, TypeError):
                pass  # this pair's data was lost; a pair nested under its name may not be
            walk(item, f"{name}/")

    with file:
        walk(file, "")
    return found


def _not_hdf5_message(path: Path) -> str:
    return f"{path} is not a readable HDF5 match cache (delete it or rerun with --overwrite)"


def _group_key(name: str) -> str:
    """The HDF5 path of a pair; rejects names whose '/'-parts would collapse or escape."""
    parts = str(name).split("/")
    if not name or any(part in ("", ".", "..") for part in parts):
        raise ValueError(f"invalid pair name {name!r}: '/'-separated parts must be non-empty")
    return "/".join(parts)


def _is_complete(item: h5py.HLObject | None) -> bool:
    return isinstance(item, h5py.Group) and int(item.attrs.get(COMPLETE_ATTR, 0)) == 1


def _clear_entry(group: h5py.Group) -> None:
    # The completion mark goes first, so the entry is never complete while half-cleared.
    if COMPLETE_ATTR in group.attrs:
        del group.attrs[COMPLETE_ATTR]
    for attr in list(group.attrs):
        del group.attrs[attr]
    for dataset in DATASETS:
        if dataset in group:
            del group[dataset]


def _plain(value: object) -> object:
    """HDF5 attribute -> plain Python scalar / str, or a numpy array for sequences."""
    if isinstance(value, bytes):
        return value.decode("utf-8")
    if isinstance(value, np.generic):
        return value.item()
    return value
