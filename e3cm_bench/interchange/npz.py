"""A folder of ``<pair name>.npz`` (the names of per_pair.csv, e.g. ``v_boat/1-3.npz``), each
holding ``keypoints0``, ``keypoints1`` (N x 2, matched rows, pixel-centre convention) and
optionally ``scores`` (N): what ``import --npz`` reads and ``export --to npz`` writes."""

from __future__ import annotations

import hashlib
import zipfile
from pathlib import Path

import numpy as np

from e3cm_bench.ground.files import file_sha256, save_npz
from e3cm_bench.ground.matches import Matches, MatchesError
from e3cm_bench.interchange.base import MissingPair, source_identity, check_declared, real_points, score_array
from e3cm_bench.interchange.pixels import from_origin, resolve_origin, to_origin
from e3cm_bench.interchange.registry import Format, register


@register
class NpzFormat(Format):
    name = "npz"
    origin = "center"
    reads = ("DIR",)
    import_help = "Folder of <pair name>.npz (keypoints0, keypoints1, optional scores)."
    writes = "the folder import --npz reads"
    labelled_by = "folder"

    def source(self, paths, benchmark: str, origin: str | None = None):
        return NpzSource(*paths, origin=origin)

    def write(self, out: Path, items: list, origin: str, job) -> list[Path]:
        return write_npz(out, items, origin)

    def targets(self, out: Path, pair_names: list[str]) -> list[Path]:
        # a pair's name may hold folders, which could reach into a run under OUT
        return [out / f"{name}.npz" for name in pair_names]

    def label(self, source) -> str:
        return Path(source.folder).resolve().name  # the folder is the method's own, whatever its name


KEYS = ("keypoints0", "keypoints1", "scores")


def load_npz(path: Path, keys=KEYS) -> dict[str, np.ndarray]:
    """The named arrays of an .npz, each array's header read and its declared size checked
    before its data (a 2 MB file may declare gigabytes of zeros); never a pickle."""
    arrays = {}
    with zipfile.ZipFile(path) as archive:
        members = {name[:-4]: name for name in archive.namelist() if name.endswith(".npy")}
        missing = [k for k in keys[:2] if k not in members]
        if missing:
            raise MatchesError(f"no {', '.join(missing)} (it holds {', '.join(sorted(members)) or 'nothing'})")
        for key in (k for k in keys if k in members):
            with archive.open(members[key]) as f:
                version = np.lib.format.read_magic(f)
                read_header = (
                    np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
                )
                shape, _, dtype = read_header(f)
                check_declared(key, shape, dtype.itemsize)
            with archive.open(members[key]) as f:
                arrays[key] = np.lib.format.read_array(f, allow_pickle=False)
    return arrays


class NpzSource:
    """A folder of <pair name>.npz (module docstring)."""

    format = "npz"
    per_pair = True  # one file per pair: a resume may add or fix the files of pairs not yet imported

    def __init__(self, folder: Path, origin: str | None = None) -> None:
        self.folder = Path(folder)
        self.origin = resolve_origin(NpzFormat, origin)
        if not self.folder.is_dir():
            raise ValueError(f"{self.folder}: not a folder")

    def path(self, pair_name: str) -> Path:
        return self.folder / f"{pair_name}.npz"

    def files(self, pairs) -> dict[str, str]:
        """Each pair's file's sha256 (only those of the benchmark's pairs: the folder may hold more)."""
        return {f"{p.name}.npz": file_sha256(self.path(p.name)) for p in pairs if self.path(p.name).is_file()}

    def identity(self, files: dict[str, str]) -> dict:
        """One digest for the folder: each file's hash by name."""
        digest = hashlib.sha256("\n".join(f"{k} {v}" for k, v in sorted(files.items())).encode()).hexdigest()
        return source_identity({"format": self.format, "n_files": len(files), "sha256": digest}, self.origin,
                               NpzFormat.origin)

    def location(self) -> dict:
        return {"folder": str(self.folder), "pixel_origin": self.origin}

    def expected(self, pair, root: Path) -> str:
        return str(self.path(pair.name))

    def read(self, pair, root: Path) -> Matches:
        path = self.path(pair.name)
        if not path.is_file():
            raise MissingPair(f"{path}: not found")
        try:
            data = load_npz(path)
            k0, k1 = (real_points(data[k], k) for k in KEYS[:2])
            scores = score_array(data["scores"], "scores", len(k0)) if "scores" in data and len(k0) == len(k1) else None
            if self.origin != NpzFormat.origin:
                k0, k1 = from_origin(k0, self.origin), from_origin(k1, self.origin)
            return Matches(k0, k1, scores)
        except MatchesError as error:
            raise MatchesError(f"{path}: {error}") from None
        except (OSError, ValueError, zipfile.BadZipFile, EOFError) as error:
            raise MatchesError(f"{path}: not a readable .npz ({error})") from None


def write_npz(out: Path, items, origin: str | None = None) -> list[Path]:
    origin = resolve_origin(NpzFormat, origin)
    written = []
    for item in items:
        k0, k1 = item.matches.keypoints0, item.matches.keypoints1
        if origin != NpzFormat.origin:
            k0, k1 = to_origin(k0, origin), to_origin(k1, origin)
        path = out / f"{item.name}.npz"
        path.parent.mkdir(parents=True, exist_ok=True)
        written.append(save_npz(path, keypoints0=k0, keypoints1=k1, scores=item.matches.scores))
    return written
