"""`e3cm-bench download` against servers on 127.0.0.1 that never finish: an endless body stops
at the size the source declares (WxBS and EVD declare theirs), and a server that trickles its
headers or its body a byte at a time is given up on at the overall deadline
(E3CM_BENCH_DOWNLOAD_DEADLINE), at the headers' deadline or when the body stalls; each in one
line, the part kept for a resume, nothing recorded."""

from __future__ import annotations

import socket
import threading
import time
from pathlib import Path

import pytest

import e3cm_bench.data.download as dl
from e3cm_bench.datasets.sources import SOURCES
from helpers import invoke, one_line_error


class RawServer:
    """A TCP server on 127.0.0.1 whose every connection is given to `serve(connection)` (after
    the request has been read), for answers http.server cannot send: headers a byte at a time."""

    def __init__(self, serve) -> None:
        self.serve = serve
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.url = f"http://127.0.0.1:{self.listener.getsockname()[1]}"
        self.stop = threading.Event()
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while not self.stop.is_set():
            try:
                connection, _ = self.listener.accept()
            except OSError:
                return
            threading.Thread(target=self._handle, args=(connection,), daemon=True).start()

    def _handle(self, connection: socket.socket) -> None:
        with connection:
            request = b""
            while b"\r\n\r\n" not in request:
                data = connection.recv(4096)
                if not data:
                    return
                request += data
            try:
                self.serve(connection, self.stop)
            except OSError:
                pass  # the client hung up: what these tests want

    def __enter__(self) -> RawServer:
        return self

    def __exit__(self, *exc) -> None:
        self.stop.set()
        self.listener.close()


def trickle(connection, stop, data: bytes, every: float, for_s: float) -> None:
    """`data` a byte at a time, one every `every` seconds, for at most `for_s` seconds."""
    started = time.monotonic()
    for byte in data:
        if stop.is_set() or time.monotonic() - started > for_s:
            return
        connection.sendall(bytes([byte]))
        time.sleep(every)


def slow_headers(connection, stop) -> None:
    trickle(connection, stop, b"HTTP/1.1 200 OK\r\nX-Slow: " + b"a" * 10_000 + b"\r\n\r\n", 0.2, 40)


def slow_body(connection, stop) -> None:
    connection.sendall(b"HTTP/1.1 200 OK\r\nContent-Length: 100000\r\nConnection: close\r\n\r\n")
    trickle(connection, stop, b"\0" * 100_000, 0.2, 40)


def endless(connection, stop) -> None:
    """No length, then zeros until 80 MB (a bound for this test's sake; the probe's server never stopped)."""
    connection.sendall(b"HTTP/1.1 200 OK\r\nConnection: close\r\n\r\n")
    block = b"\0" * (1 << 20)
    for _ in range(80):
        if stop.is_set():
            return
        connection.sendall(block)


def download(name: str, data: Path, url: str):
    started = time.monotonic()
    result = invoke("download", name, "--to", data, "--from", url)
    return result, time.monotonic() - started


def test_an_endless_body_stops_at_the_size_evd_declares(tmp_path):
    """Before: EVD declared no size, so an endless body was read until something outside stopped it."""
    cap = dl.max_bytes(SOURCES["evd"].parts[0].size)
    assert cap < 50 << 20
    with RawServer(endless) as server:
        result, _ = download("evd", tmp_path / "data", server.url + "/EVD.zip")
    line = one_line_error(result)
    assert f"sent more than the {cap} bytes this file may have; nothing is kept" in line
    assert not list((tmp_path / "data" / ".downloads").iterdir())


@pytest.mark.parametrize("name", ["evd", "hpatches"])
def test_headers_sent_a_byte_at_a_time_meet_the_deadline_set_by_the_environment(tmp_path, monkeypatch, name):
    """Before: the deadline was checked only between body reads, so a server trickling its
    headers (a byte every 0.2 s here, every 2 s in the probe) was waited on for as long as it
    went on; now E3CM_BENCH_DOWNLOAD_DEADLINE=2 holds however the bytes come."""
    monkeypatch.setenv(dl.DEADLINE_ENV, "2")
    with RawServer(slow_headers) as server:
        result, took = download(name, tmp_path / "data", server.url + "/file.zip")
    line = one_line_error(result)
    assert "not finished after 2 s (the deadline: set by E3CM_BENCH_DOWNLOAD_DEADLINE)" in line, line
    assert took < 10, took
    assert dl.read_lock(tmp_path / "data") == {}


def test_a_body_sent_a_byte_at_a_time_meets_the_deadline_and_the_part_is_kept(tmp_path, monkeypatch):
    monkeypatch.setenv(dl.DEADLINE_ENV, "2")
    with RawServer(slow_body) as server:
        result, took = download("evd", tmp_path / "data", server.url + "/EVD.zip")
    line = one_line_error(result)
    assert "not finished after 2 s" in line and "is kept: rerun the same command to resume" in line
    assert took < 10, took
    assert 0 < (tmp_path / "data" / ".downloads" / "EVD.zip.part").stat().st_size < 100


def test_headers_that_do_not_arrive_in_time_are_given_up_on_without_a_deadline_set(tmp_path, monkeypatch):
    monkeypatch.setattr(dl, "HEADERS_S", 1)
    with RawServer(slow_headers) as server:
        result, took = download("evd", tmp_path / "data", server.url + "/EVD.zip")
    line = one_line_error(result)
    assert "sent no complete answer (status line and headers) within 1 s" in line and took < 10


def test_a_stalled_body_is_given_up_on_without_a_deadline_set(tmp_path, monkeypatch):
    """A byte every 0.2 s: 5 bytes a second, fewer than the 1000 this test asks of each second."""
    monkeypatch.setattr(dl, "STALL_S", 1)
    monkeypatch.setattr(dl, "STALL_BYTES", 1000)
    with RawServer(slow_body) as server:
        result, took = download("evd", tmp_path / "data", server.url + "/EVD.zip")
    line = one_line_error(result)
    assert "bytes in the last 1 s (fewer than 1000 in 1 s: stalled" in line and took < 10
    assert (tmp_path / "data" / ".downloads" / "EVD.zip.part").is_file()


@pytest.mark.parametrize("value", ["0", "-5", "soon", "inf"])
def test_a_deadline_that_is_not_a_positive_number_is_one_line(tmp_path, monkeypatch, value):
    monkeypatch.setenv(dl.DEADLINE_ENV, value)
    line = one_line_error(invoke("download", "evd", "--to", tmp_path, "--from", "http://127.0.0.1:9/EVD.zip"))
    assert f"E3CM_BENCH_DOWNLOAD_DEADLINE={value!r}: expected a positive number of seconds" in line


def test_every_fetched_part_has_a_bounded_size():
    for source in SOURCES.values():
        for part in source.parts:
            if part.url is not None:
                assert dl.max_bytes(part.size) <= dl.UNKNOWN_SIZE_CAP, (source.name, part.file)
    assert all(SOURCES[name].parts[0].size for name in ("wxbs", "evd", "hpatches", "yfcc"))


@pytest.mark.parametrize("name, folder", [("wxbs", "WxBS"), ("evd", "EVD")])
def test_the_declared_sizes_hold_the_real_data(shared_data, name, folder):
    """The unpacked copies (WxBS without one of its 34 pairs) fit in the size declared, and the
    cap leaves room for the zip's overhead."""
    unpacked = sum(p.stat().st_size for p in (shared_data / folder).rglob("*") if p.is_file())
    size = SOURCES[name].parts[0].size
    assert unpacked < size < 1.2 * unpacked
