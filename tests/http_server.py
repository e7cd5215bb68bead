"""A web server on 127.0.0.1 whose answers a test writes, for the download tests (cli/) and the
WxBS and EVD release downloads (benchmarks/)."""

from __future__ import annotations

import http.server
import threading


def answer(handler, status: int, body: bytes, headers: dict | None = None, length: int | None = -1) -> None:
    """Send status, headers and body; length -1: the body's true Content-Length, None: none."""
    handler.send_response(status)
    for key, value in (headers or {}).items():
        handler.send_header(key, value)
    if length is not None:
        handler.send_header("Content-Length", str(len(body) if length == -1 else length))
    handler.send_header("Connection", "close")
    handler.end_headers()
    try:
        handler.wfile.write(body)
    except OSError:
        pass  # the client stopped reading (a cap or a deadline): what this test wants


class Server:
    """routes: path -> function(handler, range_header or None, how many times this path was asked)."""

    def __init__(self, routes: dict):
        self.routes, self.requests = routes, []
        server = self

        class Handler(http.server.BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def log_message(self, *args):
                pass

            def do_GET(self):  # noqa: N802
                server.requests.append((self.path, self.headers.get("Range")))
                asked = sum(1 for path, _ in server.requests if path == self.path)
                route = server.routes.get(self.path)
                if route is None:
                    answer(self, 404, b"")
                else:
                    route(self, self.headers.get("Range"), asked)
                self.close_connection = True

        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.httpd.shutdown()
        self.httpd.server_close()
