"""The HTTP pieces of a download: connections whose sockets the deadline's watchdog can shut
(the download.Deadline passed to them; not imported here, as download imports this module),
and what a server's answer says of the bytes it sends (a 206's range, a 416's whole length)."""

from __future__ import annotations

import http.client
import re
import socket
from pathlib import Path
from urllib.error import HTTPError
from urllib.request import HTTPHandler, HTTPSHandler

from e3cm_bench.data.folder import DownloadError


def shut(sock: socket.socket) -> None:
    try:
        sock.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass  # already closed


def _watched(connection_class, deadline):
    class Watched(connection_class):
        def connect(self) -> None:
            super().connect()
            deadline.watch(self.sock)
    return Watched


class WatchedHTTP(HTTPHandler):
    def __init__(self, deadline) -> None:
        super().__init__()
        self.deadline = deadline

    def http_open(self, req):
        return self.do_open(_watched(http.client.HTTPConnection, self.deadline), req)


class WatchedHTTPS(HTTPSHandler):
    def __init__(self, deadline) -> None:
        super().__init__()
        self.deadline = deadline

    def https_open(self, req):
        return self.do_open(_watched(http.client.HTTPSConnection, self.deadline), req, context=self._context)


def whole_length(error: HTTPError) -> int | None:
    """The file's length from a 416's Content-Range (``bytes */LENGTH``), else None."""
    match = re.fullmatch(r"\s*bytes\s+\*/(\d+)\s*", error.headers.get("Content-Range") or "")
    return int(match.group(1)) if match else None


def body_range(url: str, response, offset: int, part: Path) -> tuple[int, int | None, int | None]:
    """Where the body starts in the file, where it ends (None: at the connection's end) and
    the file's whole length (None where unknown), checked against what was asked."""
    length = response.headers.get("Content-Length")
    length = int(length) if length is not None and length.strip().isdigit() else None
    if response.status != 206:
        return 0, length, length  # the whole file (a server that ignores ranges starts over)
    content_range = response.headers.get("Content-Range") or ""
    match = re.fullmatch(r"\s*bytes\s+(\d+)-(\d+)/(\d+|\*)\s*", content_range)
    first, last = (int(match.group(1)), int(match.group(2))) if match else (-1, -1)
    total = int(match.group(3)) if match and match.group(3) != "*" else None
    if not match or last < first or (total is not None and last >= total) or \
            (length is not None and length != last - first + 1):
        raise DownloadError(f"{url}: a partial answer (206) with Content-Range {content_range!r} and Content-Length "
                            f"{length}, which do not agree; {part} is kept: rerun, or pass --from another mirror")
    if first != offset and first != 0:
        part.unlink(missing_ok=True)
        raise DownloadError(f"{url}: asked for the bytes from {offset} on, the server sent {first}-{last}; {part} is "
                            "dropped: rerun the same command to fetch the file from the start")
    # first == 0: the server restarted the file; it is written from the start, never appended
    return first, last + 1, total
