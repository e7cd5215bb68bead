"""`e3cm-bench download` against a server on 127.0.0.1 started here: fetch, verify,
resume after a dropped connection, refuse bad hashes and unsafe archives, one line for
HTTP and connection errors. Nothing leaves the machine."""

from __future__ import annotations

import http.server
import io
import json
import socket
import tarfile
import threading
import zipfile
from pathlib import Path

import pytest

from e3cm_bench.datasets.sources import Part, Source
from e3cm_bench.data.download import LOCK_FILE, DownloadError, download
from helpers import invoke, one_line_error


def hpatches_zip(shared_data: Path) -> bytes:
    """A small archive in HPatches' layout: the shared sequences under hpatches-sequences-release/."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as zf:
        for path in sorted((shared_data / "hpatches-sequences-release").rglob("*")):
            if path.is_file():
                zf.write(path, "hpatches-sequences-release/" + path.relative_to(shared_data / "hpatches-sequences-release").as_posix())
    return buffer.getvalue()


class Server:
    """Serves `files` (path -> bytes). drop_once: the first GET of a path sends half its bytes
    (announcing all) and closes; ranges: honour Range requests (206) or always send 200."""

    def __init__(self, files: dict[str, bytes], drop_once: bool = False, ranges: bool = True):
        self.files, self.drop_once, self.ranges, self.requests = files, drop_once, ranges, []
        server = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def log_message(self, *args):
                pass

            def do_GET(self):  # noqa: N802
                server.requests.append((self.path, self.headers.get("Range")))
                if self.path.startswith("/status/"):
                    self.send_error(int(self.path.rsplit("/", 1)[1]))
                    return
                data = server.files.get(self.path)
                if data is None:
                    self.send_error(404)
                    return
                start = 0
                if server.ranges and self.headers.get("Range"):
                    start = int(self.headers["Range"].split("=")[1].split("-")[0])
                    self.send_response(206)
                    self.send_header("Content-Range", f"bytes {start}-{len(data) - 1}/{len(data)}")
                else:
                    self.send_response(200)
                body = data[start:]
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                if server.drop_once:
                    server.drop_once = False
                    self.wfile.write(body[: len(body) // 2])
                    self.wfile.flush()
                    self.connection.shutdown(socket.SHUT_RDWR)
                    return
                self.wfile.write(body)

        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def close(self):
        self.httpd.shutdown()


def source(url: str, sha256: str | None = None, name: str = "hp") -> Source:
    return Source(name, "hpatches", "hpatches-sequences-release",
                  (Part("hpatches-sequences-release.zip", url, sha256),), expected={"sequences": 3, "images": 18})


def test_download_verifies_records_the_hash_and_unpacks(shared_data, tmp_path):
    data = hpatches_zip(shared_data)
    server = Server({"/hp.zip": data})
    try:
        root = download(source(server.url + "/hp.zip"), tmp_path / "data")
        assert sorted(p.name for p in root.iterdir() if p.is_dir()) == ["i_leuven", "v_boat", "v_graffiti"]
        assert (root / "v_boat" / "H_1_2").read_bytes() == (shared_data / "hpatches-sequences-release/v_boat/H_1_2").read_bytes()
        lock = json.loads((tmp_path / "data" / LOCK_FILE).read_text())
        import hashlib

        assert lock == {"hpatches-sequences-release.zip": hashlib.sha256(data).hexdigest()}
        from e3cm_bench.data.download import check

        assert check(source(""), tmp_path / "data").endswith("complete (3 sequences, 18 images)")
        # the server's file changes: the recorded hash refuses it and keeps it aside
        server.files["/hp.zip"] = data[:-10] + b"x" * 10
        (tmp_path / "data" / ".downloads" / "hpatches-sequences-release.zip").unlink()
        (root / ".complete").unlink()
        with pytest.raises(DownloadError, match=r"sha256 \w+ is not the \w+ recorded in .* by the first download"):
            download(source(server.url + "/hp.zip"), tmp_path / "data")
        assert (tmp_path / "data" / ".downloads" / "hpatches-sequences-release.zip.bad").is_file()
    finally:
        server.close()


@pytest.mark.parametrize("ranges", [True, False])
def test_a_dropped_connection_resumes_to_the_same_bytes(shared_data, tmp_path, ranges):
    data = hpatches_zip(shared_data)
    server = Server({"/hp.zip": data}, drop_once=True, ranges=ranges)
    try:
        with pytest.raises(DownloadError, match=r"the connection dropped at \d+ of \d+ bytes; .* rerun the same command to resume"):
            download(source(server.url + "/hp.zip"), tmp_path / "data")
        part = tmp_path / "data" / ".downloads" / "hpatches-sequences-release.zip.part"
        assert 0 < part.stat().st_size < len(data)
        download(source(server.url + "/hp.zip"), tmp_path / "data")
        assert (tmp_path / "data" / ".downloads" / "hpatches-sequences-release.zip").read_bytes() == data
        # with ranges the rerun asked for the rest only; without, the server sent it all again
        assert server.requests[-1][1] == f"bytes={len(data) // 2}-"
    finally:
        server.close()


def test_a_pinned_hash_that_does_not_match_is_refused(shared_data, tmp_path):
    server = Server({"/hp.zip": hpatches_zip(shared_data)})
    try:
        with pytest.raises(DownloadError, match=r"is not the 0{64} pinned in e3cm-bench; the file is kept aside"):
            download(source(server.url + "/hp.zip", sha256="0" * 64), tmp_path / "data")
        assert not (tmp_path / "data" / "hpatches-sequences-release").exists()
    finally:
        server.close()


def test_unsafe_archive_members_are_refused_and_nothing_is_written_outside(tmp_path):
    evil = io.BytesIO()
    with zipfile.ZipFile(evil, "w") as zf:
        zf.writestr("top/ok.txt", "fine")
        zf.writestr("top/../../escaped.txt", "bad")
    link = io.BytesIO()
    with tarfile.open(fileobj=link, mode="w") as tf:
        member = tarfile.TarInfo("top/link")
        member.type, member.linkname = tarfile.SYMTYPE, "/etc/passwd"
        tf.addfile(member)
    for name, blob, says in (("evil.zip", evil.getvalue(), "would be written outside the folder"),
                             ("link.tar", link.getvalue(), "is a link or a device file")):
        archive = tmp_path / name
        archive.write_bytes(blob)
        with pytest.raises(DownloadError, match=says):
            download(source(str(archive)), tmp_path / "data" / name)
        assert not (tmp_path / "escaped.txt").exists() and not (tmp_path / "data" / "escaped.txt").exists()
        assert not (tmp_path / "data" / name / "hpatches-sequences-release").exists()


def test_http_errors_and_a_refused_connection_are_one_line(tmp_path, monkeypatch):
    import e3cm_bench.datasets.sources as sources

    server = Server({})
    with socket.socket() as probe:  # a port nothing listens on
        probe.bind(("127.0.0.1", 0))
        closed = f"http://127.0.0.1:{probe.getsockname()[1]}/x.zip"
    try:
        for url, says in ((server.url + "/missing.zip", "HTTP 404"), (server.url + "/status/500", "HTTP 500"),
                          (closed, "cannot connect")):
            monkeypatch.setitem(sources.SOURCES, "hp", source(url))
            line = one_line_error(invoke("download", "hp", "--to", tmp_path / "d"))
            assert url in line and says in line
    finally:
        server.close()


def test_from_a_file_already_downloaded_and_the_manual_steps(shared_data, tmp_path, monkeypatch):
    import e3cm_bench.datasets.sources as sources

    archive = tmp_path / "by-hand.zip"
    archive.write_bytes(hpatches_zip(shared_data))
    monkeypatch.setitem(sources.SOURCES, "hp", source("https://example.invalid/hp.zip"))
    result = invoke("download", "hp", "--to", tmp_path / "d", "--from", archive)
    assert result.exit_code == 0 and "complete (3 sequences, 18 images)" in result.output
    line = one_line_error(invoke("download", "scannet-1500", "--to", tmp_path / "d"))
    assert "Google Drive" in line and "--check" in line
    line = one_line_error(invoke("download", "hpatches", "--to", tmp_path / "empty", "--check"))
    assert "not found; e3cm-bench download hpatches" in line


def test_datasets_reports_complete_partial_and_missing_and_commands_find_the_data(shared_data, tmp_path, monkeypatch):
    import e3cm_bench.datasets.sources as sources

    data = tmp_path / "data"
    (data / "hpatches-sequences-release").mkdir(parents=True)
    for sequence in ("v_boat", "v_graffiti", "i_leuven"):
        (data / "hpatches-sequences-release" / sequence).symlink_to(shared_data / "hpatches-sequences-release" / sequence)
    monkeypatch.setenv("E3CM_BENCH_DATA", str(data))
    text = invoke("datasets").output
    assert f"data folder: {data}" in " ".join(text.split())  # wrapped at 80 columns
    assert "hpatches: incomplete at" in text and "sequences 3 of 116, images 18 of 696" in " ".join(text.split())
    assert "yfcc: missing at" in text and "scannet-1500: missing at" in text
    # a benchmark command without --root looks there, and says what fixes an incomplete copy
    line = one_line_error(invoke("hpatches", "--out", tmp_path / "run", "--matcher", "sift", "--limit", 1))
    assert "no --root given and hpatches at" in line and f"e3cm-bench download hpatches --to {data}" in line
    # a copy that holds what it should is complete, and is found
    small = Source("hpatches", "hpatches", "hpatches-sequences-release",
                   sources.SOURCES["hpatches"].parts, expected={"sequences": 3, "images": 18})
    monkeypatch.setitem(sources.SOURCES, "hpatches", small)
    text = invoke("datasets").output
    assert "hpatches at" in text and "complete (3 sequences, 18 images); no download recorded (placed by hand)" in " ".join(text.split())
    result = invoke("hpatches", "--out", tmp_path / "run", "--matcher", "sift", "--limit", 1, "--max-side", 320)
    assert result.exit_code == 0 and (tmp_path / "run" / "summary.csv").is_file()


def test_megadepth_in_gluefactorys_layout_downloads_and_is_found_without_root(shared_data, tmp_path, monkeypatch):
    """glue-factory's megadepth1500.zip layout (the real KITTI pairs written in it), served here:
    downloaded, unpacked, listed by `datasets`, and found by `megadepth` without --root where
    LoFTR's layout is absent."""
    import dataclasses

    import e3cm_bench.datasets.sources as sources
    from helpers import gluefactory_layout

    kitti = shared_data / "megadepth_test_1500"
    staging = tmp_path / "staging" / "megadepth1500"
    n = gluefactory_layout([kitti / "scene_info" / "kitti00_seq.npz"], staging,
                           lambda relative, destination: destination.write_bytes((kitti / relative).read_bytes()))
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as zf:
        for path in sorted(staging.rglob("*")):
            if path.is_file():
                zf.write(path, path.relative_to(staging.parent).as_posix())
    server = Server({"/megadepth1500.zip": buffer.getvalue()})
    try:
        for name in ("megadepth-1500", "megadepth-1500-gluefactory"):
            monkeypatch.setitem(sources.SOURCES, name, dataclasses.replace(sources.SOURCES[name], expected={"pairs": n}))
        data = tmp_path / "data"
        result = invoke("download", "megadepth-1500-gluefactory", "--to", data, "--from", server.url + "/megadepth1500.zip")
        assert result.exit_code == 0 and (data / "megadepth1500" / "views.txt").is_file()
        monkeypatch.setenv("E3CM_BENCH_DATA", str(data))
        text = " ".join(invoke("datasets").output.split())
        assert "megadepth-1500: missing at" in text
        assert f"megadepth-1500-gluefactory at {data / 'megadepth1500'}: complete ({n} pairs); sha256 recorded" in text
        result = invoke("megadepth", "--out", tmp_path / "run", "--matcher", "sift", "--limit", 1, "--max-side", 320)
        assert result.exit_code == 0
        config = (tmp_path / "run" / "config.yaml").read_text()
        assert "layout: gluefactory" in config and str(data / "megadepth1500" / "pairs.txt") in config
    finally:
        server.close()
    # neither layout present: the line names both download commands
    monkeypatch.setenv("E3CM_BENCH_DATA", str(tmp_path / "empty"))
    line = one_line_error(invoke("megadepth", "--out", tmp_path / "run2", "--matcher", "sift"))
    assert "e3cm-bench download megadepth-1500 --to" in line and "or e3cm-bench download megadepth-1500-gluefactory --to" in line
