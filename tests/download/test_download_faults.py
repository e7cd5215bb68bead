"""`e3cm-bench download` at the level of the command, against servers on 127.0.0.1 that misbehave on purpose: a broken first download
never becomes the trust anchor, two downloads never share a data folder, a download is
bounded in bytes, unpacked bytes and time, and every failure is one line."""

from __future__ import annotations

import errno
import hashlib
import io
import json
import shutil
import subprocess
import sys
import tarfile
import threading
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

import e3cm_bench.datasets.sources as sources
import e3cm_bench.data.download as dl
from e3cm_bench.datasets.sources import Part, Source
from helpers import flat, invoke, one_line_error
from http_server import Server, answer

COMPLETE = "complete (1 sequences, 6 images)"


def tiny_hpatches(kind: str = "zip") -> bytes:
    """One HPatches-format sequence (six 64x64 noise images, identity homographies) as a zip
    or a tar.gz under hp-data/: about 74 KB that hardly compress, so a cut is a real cut."""
    rng = np.random.default_rng(0)
    files = {}
    for i in range(1, 7):
        files[f"hp-data/v_tiny/{i}.ppm"] = b"P6\n64 64\n255\n" + rng.integers(0, 256, 64 * 64 * 3, dtype=np.uint8).tobytes()
        if i > 1:
            files[f"hp-data/v_tiny/H_1_{i}"] = b"1 0 0\n0 1 0\n0 0 1\n"
    buffer = io.BytesIO()
    if kind == "zip":
        with zipfile.ZipFile(buffer, "w", zipfile.ZIP_STORED) as zf:
            for name, data in files.items():
                zf.writestr(name, data)
    else:
        with tarfile.open(fileobj=buffer, mode="w:gz") as tf:
            for name, data in files.items():
                info = tarfile.TarInfo(name)
                info.size = len(data)
                tf.addfile(info, io.BytesIO(data))
    return buffer.getvalue()


GOOD = tiny_hpatches()
GOOD_SHA = hashlib.sha256(GOOD).hexdigest()


def good(handler, range_header, asked):
    """A correct server: ranges honoured (206 with the asked start), else the whole file."""
    if range_header:
        start = int(range_header.split("=")[1].split("-")[0])
        answer(handler, 206, GOOD[start:], {"Content-Range": f"bytes {start}-{len(GOOD) - 1}/{len(GOOD)}"})
    else:
        answer(handler, 200, GOOD)


def first_cut_at_half(then):
    """The first GET announces the whole file and sends half of it; later ones go to `then`."""
    def route(handler, range_header, asked):
        if asked == 1:
            answer(handler, 200, GOOD[: len(GOOD) // 2], length=len(GOOD))
        else:
            then(handler, range_header, asked)
    return route


@pytest.fixture
def hp(monkeypatch):
    """A source `hp` (one archive, no pinned hash, expected about GOOD's size) whose complete
    copy is the tiny sequence; returns a function that swaps its Part for a test's."""
    def use(**changes):
        fields = {"file": "hp.zip", "url": "https://example.invalid/hp.zip", "size": len(GOOD), **changes}
        monkeypatch.setitem(sources.SOURCES, "hp", Source("hp", "hpatches", "hp-data", (Part(**fields),),
                                                          expected={"sequences": 1, "images": 6}))
    use()
    return use


def lock_of(data: Path) -> dict | None:
    path = data / dl.LOCK_FILE
    return json.loads(path.read_text()) if path.exists() else None


# ----------------------------------------------------------------------------- the trust anchor


@pytest.mark.parametrize("case", ["short content-length", "cut without content-length", "bad crc"])
def test_a_damaged_first_download_records_no_hash_and_the_good_file_is_then_trusted(hp, tmp_path, case):
    """Before: each of these was renamed as complete and its sha256 written into the lock; the
    good file was then refused (moved to .bad). Now: one line, the archive set aside, no hash,
    nothing unpacked, and a rerun from a good mirror records the good file's hash."""
    data = tmp_path / "data"
    crc = bytearray(GOOD)
    crc[GOOD.index(b"P6\n64 64") + 100] ^= 0xFF  # one byte of a stored member's data: its CRC-32 no longer holds
    routes = {
        "short content-length": lambda h, r, n: answer(h, 200, GOOD[:-5000], length=len(GOOD) - 5000),
        "cut without content-length": lambda h, r, n: answer(h, 200, GOOD[: len(GOOD) // 2], length=None),
        "bad crc": lambda h, r, n: answer(h, 200, bytes(crc)),
    }
    with Server({"/broken.zip": routes[case], "/good.zip": good}) as server:
        line = one_line_error(invoke("download", "hp", "--to", data, "--from", server.url + "/broken.zip"))
        assert "damaged or cut short" in line and "no hash was recorded" in line, line
        assert lock_of(data) is None
        assert (data / ".downloads" / "hp.zip.bad").is_file() and not (data / ".downloads" / "hp.zip").exists()
        assert not (data / "hp-data").exists()
        result = invoke("download", "hp", "--to", data, "--from", server.url + "/good.zip")
    assert result.exit_code == 0, result.output
    assert COMPLETE in result.output
    assert lock_of(data) == {"hp.zip": GOOD_SHA}


def test_a_damaged_archive_whose_hash_an_earlier_version_recorded_is_named(hp, tmp_path):
    """The state the earlier versions left: a cut zip in .downloads with its hash in the lock.
    It is set aside, and the line says which entry of the lock would refuse the good file."""
    data = tmp_path / "data"
    (data / ".downloads").mkdir(parents=True)
    (data / ".downloads" / "hp.zip").write_bytes(GOOD[:-5000])
    (data / dl.LOCK_FILE).write_text(json.dumps({"hp.zip": hashlib.sha256(GOOD[:-5000]).hexdigest()}))
    line = one_line_error(invoke("download", "hp", "--to", data))
    assert "damaged or cut short" in line and f"recorded in {data / dl.LOCK_FILE} by an earlier download" in line
    assert "remove the 'hp.zip' entry there first" in line
    assert (data / ".downloads" / "hp.zip.bad").is_file() and not (data / "hp-data").exists()


def test_a_resume_that_the_server_answers_wrongly_never_appends_to_the_part(hp, tmp_path):
    """A 206 that restarts at byte 0 (before: appended, the YFCC list grew to 5961 lines, hash
    recorded) and a 416 whose Content-Range says a longer file (before: the half part renamed as
    complete): both now fetch the file whole; a 206 from another byte is refused in one line."""
    data = tmp_path / "data"

    def from_zero(handler, range_header, asked):
        answer(handler, 206, GOOD, {"Content-Range": f"bytes 0-{len(GOOD) - 1}/{len(GOOD)}"})

    def refuse_range(handler, range_header, asked):
        if range_header:
            answer(handler, 416, b"", {"Content-Range": f"bytes */{len(GOOD)}"})
        else:
            answer(handler, 200, GOOD)

    def elsewhere(handler, range_header, asked):
        start = len(GOOD) // 2 - 100
        answer(handler, 206, GOOD[start:], {"Content-Range": f"bytes {start}-{len(GOOD) - 1}/{len(GOOD)}"})

    routes = {"/zero.zip": first_cut_at_half(from_zero), "/416.zip": first_cut_at_half(refuse_range),
              "/elsewhere.zip": first_cut_at_half(elsewhere)}
    with Server(routes) as server:
        for path in ("/zero.zip", "/416.zip"):
            shutil.rmtree(data, ignore_errors=True)
            line = one_line_error(invoke("download", "hp", "--to", data, "--from", server.url + path))
            assert f"the connection dropped at {len(GOOD) // 2} of {len(GOOD)} bytes" in line
            result = invoke("download", "hp", "--to", data, "--from", server.url + path)
            assert result.exit_code == 0 and COMPLETE in result.output, (path, result.output)
            assert (data / ".downloads" / "hp.zip").read_bytes() == GOOD, path
            assert lock_of(data) == {"hp.zip": GOOD_SHA}, path
        assert server.requests[-2:] == [("/416.zip", f"bytes={len(GOOD) // 2}-"), ("/416.zip", None)]
        shutil.rmtree(data)
        one_line_error(invoke("download", "hp", "--to", data, "--from", server.url + "/elsewhere.zip"))
        line = one_line_error(invoke("download", "hp", "--to", data, "--from", server.url + "/elsewhere.zip"))
    assert f"asked for the bytes from {len(GOOD) // 2} on, the server sent {len(GOOD) // 2 - 100}-" in line
    assert "dropped: rerun" in line
    assert not list((data / ".downloads").iterdir()) and lock_of(data) is None


def test_a_full_disk_keeps_the_part_records_nothing_and_names_the_full_filesystem(hp, tmp_path, monkeypatch):
    """Before: the write error was swallowed, the cut zip renamed as complete, the lock left at
    0 bytes, and the line quoted the current folder's free space with "every pair already
    written resumes". Now: the data folder's free space, the download's own advice, the part
    kept; the rerun resumes from it."""
    data = tmp_path / "data"
    real_usage, real_write = shutil.disk_usage, dl._write_all
    written = []

    def usage(path):  # the data folder's filesystem has 700 MiB free, the current folder's far more
        free = 700 << 20 if str(Path(path).resolve()).startswith(str(data)) else 99_999 << 20
        return real_usage(path)._replace(free=free)

    def fill_up(fd, chunk):  # 30000 bytes fit, then the disk is full
        room = 30_000 - sum(written)
        written.append(min(room, len(chunk)))
        real_write(fd, chunk[:room])
        if len(chunk) > room:
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(shutil, "disk_usage", usage)
    monkeypatch.setattr(dl, "_write_all", fill_up)
    with Server({"/hp.zip": good}) as server:
        line = one_line_error(invoke("download", "hp", "--to", data, "--from", server.url + "/hp.zip"))
        assert f"{data}: no space left on the device (700.0 MiB free there" in line, line
        assert "rerun the same command (what was fetched is kept and resumed from)" in line and "every pair" not in line
        assert lock_of(data) is None and not (data / dl.LOCK_FILE).exists()
        assert not (data / ".downloads" / "hp.zip").exists()
        assert (data / ".downloads" / "hp.zip.part").read_bytes() == GOOD[:30_000]
        monkeypatch.setattr(dl, "_write_all", real_write)
        result = invoke("download", "hp", "--to", data, "--from", server.url + "/hp.zip")
        assert server.requests[-1] == ("/hp.zip", "bytes=30000-")
    assert result.exit_code == 0 and COMPLETE in result.output
    assert lock_of(data) == {"hp.zip": GOOD_SHA}


def test_os_error_line_quotes_the_full_filesystem_and_says_resume_only_for_run_folders(tmp_path, monkeypatch):
    from e3cm_bench.cli import os_error_line

    real_usage = shutil.disk_usage
    full = tmp_path / "full"
    full.mkdir()
    monkeypatch.setattr(shutil, "disk_usage", lambda path: real_usage(path)._replace(
        free=(3 << 20) if str(path).startswith(str(full)) else 99_999 << 20))
    error = OSError(errno.ENOSPC, "No space left on device", str(full / "report" / "index.html"))
    line = os_error_line(error)
    assert "(3.0 MiB free there)" in line and "every pair" not in line
    assert line.endswith("free some space and rerun the same command")
    assert os_error_line(error, resumes=True).endswith("every pair already written resumes")
    # a failed write() names no file: no free space quoted rather than the current folder's
    assert "MiB free" not in os_error_line(OSError(errno.ENOSPC, "No space left on device"))


# ----------------------------------------------------------------------------- one download per folder


FIRST_DOWNLOAD = """
import sys
import e3cm_bench.datasets.sources as sources
from e3cm_bench.datasets.sources import Part, Source
from e3cm_bench.cli import app
sources.SOURCES["hp"] = Source("hp", "hpatches", "hp-data", (Part("hp.zip", size=int(sys.argv[1])),),
                               expected={"sequences": 1, "images": 6})
app(sys.argv[2:], prog_name="e3cm-bench")
"""


def test_a_second_download_into_the_same_folder_is_refused_while_the_first_runs(hp, tmp_path):
    """Before: two downloads into one --to interleaved, and 1 of 6 left an incomplete copy
    marked complete. Now the data folder is locked like a run folder: the second is refused in
    one line naming the first, and the first completes alone."""
    data = tmp_path / "data"
    stalled, release = threading.Event(), threading.Event()

    def slow(handler, range_header, asked):
        handler.send_response(200)
        handler.send_header("Content-Length", str(len(GOOD)))
        handler.end_headers()
        handler.wfile.write(GOOD[:1000])
        handler.wfile.flush()
        stalled.set()
        release.wait(120)
        handler.wfile.write(GOOD[1000:])

    with Server({"/slow.zip": slow, "/good.zip": good}) as server:
        first = subprocess.Popen([sys.executable, "-c", FIRST_DOWNLOAD, str(len(GOOD)), "download", "hp", "--to",
                                  str(data), "--from", server.url + "/slow.zip"],
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            assert stalled.wait(120), "the first download never reached the server"
            line = one_line_error(invoke("download", "hp", "--to", data, "--from", server.url + "/good.zip"))
            still_running = first.poll() is None
        finally:
            release.set()
            out, err = first.communicate(timeout=120)
    assert still_running, "the first download ended before the second was refused: the test proves nothing"
    assert f"{data}: another run is using this folder (pid {first.pid}" in line and "download hp" in line
    assert line.endswith("choose another --to")
    assert first.returncode == 0, err
    assert COMPLETE in flat(out)
    assert lock_of(data) == {"hp.zip": GOOD_SHA}
    assert [path for path, _ in server.requests] == ["/slow.zip"]  # the second fetched nothing
    result = invoke("download", "hp", "--to", data)  # released: the copy is complete, nothing to fetch
    assert result.exit_code == 0 and COMPLETE in result.output


# ----------------------------------------------------------------------------- unbounded


def test_downloads_are_bounded_in_bytes_unpacked_bytes_and_time(hp, tmp_path, monkeypatch):
    """Before: an endless body and a zip bomb filled the disk, and a server trickling a byte
    every 2 s was waited for forever. Now each stops at a bound scaled to the size the source
    expects (Part.size), in one line, with nothing recorded."""
    data = tmp_path / "data"
    cap = dl.max_bytes(len(GOOD))

    def endless(handler, range_header, asked):
        handler.send_response(200)
        handler.send_header("Connection", "close")
        handler.end_headers()
        try:
            while True:
                handler.wfile.write(b"\0" * 65536)
        except OSError:
            pass

    bomb = io.BytesIO()
    with zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("hp-data/v_tiny/1.ppm", b"\0" * (40 << 20))  # 40 MiB that deflate to about 40 KB

    def trickle(handler, range_header, asked):
        handler.send_response(200)
        handler.send_header("Content-Length", str(len(GOOD)))
        handler.end_headers()
        try:
            for byte in GOOD:
                handler.wfile.write(bytes([byte]))
                handler.wfile.flush()
                time.sleep(0.2)
        except OSError:
            pass

    routes = {"/endless": endless, "/huge": lambda h, r, n: answer(h, 200, b"", length=cap + 1),
              "/bomb.zip": lambda h, r, n: answer(h, 200, bomb.getvalue()), "/trickle": trickle}
    with Server(routes) as server:
        line = one_line_error(invoke("download", "hp", "--to", data, "--from", server.url + "/endless"))
        assert f"sent more than the {cap} bytes this file may have; nothing is kept" in line
        assert not list((data / ".downloads").iterdir())
        line = one_line_error(invoke("download", "hp", "--to", data, "--from", server.url + "/huge"))
        assert f"announces {cap + 1} bytes, more than the {cap} this file may have" in line
        line = one_line_error(invoke("download", "hp", "--to", data, "--from", server.url + "/bomb.zip"))
        assert f"its members would unpack to at least {40 << 20} bytes" in line and "nothing was extracted" in line
        assert (data / ".downloads" / "hp.zip.bad").is_file()  # a rerun fetches anew, never reuses it
        assert not (data / "hp-data").exists() and not list(data.glob(".hp-data*"))
        monkeypatch.setattr(dl, "DEADLINE_BASE_S", 1)
        monkeypatch.setattr(dl, "MIN_RATE", 10**12)  # the deadline: 1 s, and the test waits little longer
        started = time.monotonic()
        line = one_line_error(invoke("download", "hp", "--to", data, "--from", server.url + "/trickle"))
        assert time.monotonic() - started < 20
    assert "not finished after 1 s" in line and "is kept: rerun the same command to resume" in line
    assert 0 < (data / ".downloads" / "hp.zip.part").stat().st_size < 100
    assert lock_of(data) is None


# ----------------------------------------------------------------------------- tracebacks


def test_a_cut_tar_gz_and_damaged_hash_records_are_one_line(hp, tmp_path):
    """Before: a truncated .tar.gz ended in "Aborted." only; a lock file holding 123, 7 or
    ["a"] was a TypeError / AttributeError in `download` and `datasets`, a 0-byte one (left by a
    full disk) "Expecting value: line 1 column 1 (char 0)". (A zip member with a bad CRC,
    before a BadZipFile: test_a_damaged_first_download_...)"""
    hp(file="hp.tar.gz")
    archive = tiny_hpatches("tar.gz")
    data = tmp_path / "data"
    with Server({"/cut.tar.gz": lambda h, r, n: answer(h, 200, archive[: len(archive) * 2 // 3]),
                 "/hp.tar.gz": lambda h, r, n: answer(h, 200, archive)}) as server:
        line = one_line_error(invoke("download", "hp", "--to", data, "--from", server.url + "/cut.tar.gz"))
        assert f"{data / '.downloads' / 'hp.tar.gz'}: damaged or cut short" in line
        assert lock_of(data) is None and not (data / "hp-data").exists()
        result = invoke("download", "hp", "--to", data, "--from", server.url + "/hp.tar.gz")
        assert result.exit_code == 0 and COMPLETE in result.output
        lock = data / dl.LOCK_FILE
        for text, says in (("123", "holds a number"), ("7", "holds a number"), ('["a"]', "holds a list"),
                           ("", "empty"), ('{"hp.tar.gz": 5}', "the entry 'hp.tar.gz' is not a sha256"),
                           ("{not json", "not JSON")):
            lock.write_text(text)
            (data / "hp-data" / ".complete").unlink()
            for args in (("download", "hp", "--to", data, "--from", server.url + "/hp.tar.gz"), ("datasets", "--to", data)):
                line = one_line_error(invoke(*args))
                assert f"{lock}: {says}" in line and "remove it and the next download records them again" in line, line
            (data / "hp-data" / ".complete").write_text("hp.tar.gz\n")
            assert lock.read_text() == text  # a damaged record is never overwritten


def test_a_published_md5_is_checked(hp, tmp_path):
    data = tmp_path / "data"
    with Server({"/hp.zip": good}) as server:
        hp(md5="0" * 32)
        line = one_line_error(invoke("download", "hp", "--to", data, "--from", server.url + "/hp.zip"))
        assert f"md5 {hashlib.md5(GOOD).hexdigest()} is not the {'0' * 32} published by the source" in line
        assert lock_of(data) is None and (data / ".downloads" / "hp.zip.bad").is_file()
        hp(md5=hashlib.md5(GOOD).hexdigest())
        result = invoke("download", "hp", "--to", data, "--from", server.url + "/hp.zip")
    assert result.exit_code == 0 and lock_of(data) == {"hp.zip": GOOD_SHA}
