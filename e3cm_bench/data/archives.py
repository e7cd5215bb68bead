"""An archive unpacked safely: members that would leave the folder, links and device files
refused, its declared size bounded, every member read to its end (a zip's CRC-32, a tar cut
short), and placed whole by a rename. Used by download.py, and by tests to make data folders."""

from __future__ import annotations

import lzma
import shutil
import stat
import tarfile
import zipfile
import zlib
from pathlib import Path, PurePosixPath

from rich.console import Console

from e3cm_bench.data.folder import FREE_RESERVE, DownloadError, disk_full, set_aside
from e3cm_bench.ground.files import write_atomically
from e3cm_bench.ground.folders import fresh_folder, remove_folder

# Image archives compress little (ppm about 2:1, jpg not at all); members declaring more than
# this many times the archive's bytes are a zip bomb, not data.
UNPACK_RATIO = 20
UNPACK_SLACK = 16 << 20


def extract(archive: Path, target: Path, console: Console | None = None) -> Path:
    """Unpack into a temporary folder beside `target`, refusing unsafe members, then rename into
    place (the archive's single top folder, or its contents, become `target`)."""
    temporary = unpack(archive, target, owned=False)
    try:
        place(temporary, target, archive)
    finally:
        remove_folder(temporary, ignore_errors=True)
    return target


def unpack(archive: Path, target: Path, owned: bool = True) -> Path:
    """The archive unpacked whole into a temporary folder beside `target` (returned): unsafe
    members refused, more than UNPACK_RATIO times the archive's bytes refused, and every member
    read to its end, which checks each zip member's CRC-32 and finds a tar cut short. A damaged
    or refused archive is moved aside (`owned`), so that a rerun fetches it again instead of
    reusing it, and said in one line."""
    temporary = fresh_folder(target.with_name(f".{target.name}.extracting"))  # never through a link
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
        remove_folder(temporary, ignore_errors=True)
        raise DownloadError(
            f"{archive}: {error}; no hash was recorded and nothing was extracted; "
            f"{set_aside(archive, owned)}: rerun to download it again, or pass --from another mirror"
        ) from None
    except (
        zipfile.BadZipFile,
        zipfile.LargeZipFile,
        tarfile.TarError,
        EOFError,
        zlib.error,
        lzma.LZMAError,
        NotImplementedError,
        OSError,
    ) as error:
        remove_folder(temporary, ignore_errors=True)
        if isinstance(error, OSError) and error.errno is not None:
            raise  # the disk or the folder, not the archive (a full disk is said by download)
        why = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise DownloadError(
            f"{archive}: damaged or cut short ({why}); no hash was recorded and nothing was extracted; "
            f"{set_aside(archive, owned)}: rerun the same command to download it again"
        ) from None
    except BaseException:
        remove_folder(temporary, ignore_errors=True)
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


def place(temporary: Path, target: Path, archive: Path) -> Path:
    """The unpacked archive's single top folder, or its contents, renamed into `target`."""
    top = list(temporary.iterdir())
    content = top[0] if len(top) == 1 and top[0].is_dir() else temporary
    remove_folder(target)  # the previous copy; a link at `target` refused, never followed
    content.rename(target)
    write_atomically(target / ".complete", lambda tmp: tmp.write_text(f"{archive.name}\n"))
    return target


def _check_member(name: str, kind: int) -> None:
    path = PurePosixPath(name.replace("\\", "/"))
    if path.is_absolute() or ".." in path.parts or (len(name) > 1 and name[1] == ":"):
        raise _Refused(f"member {name!r} would be written outside the folder")
    if kind in (stat.S_IFLNK, stat.S_IFCHR, stat.S_IFBLK, stat.S_IFIFO, stat.S_IFSOCK):
        raise _Refused(f"member {name!r} is a link or a device file")
