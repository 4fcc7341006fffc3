"""A local HTTP server handing out files: the far end of a schedule's URL source in tests.

``with serving_files({"/scan.ply": content}) as server:`` serves each path's bytes with 200
(404 for other paths) on ``server.url(path)``; ``server.files[path] = new`` changes a file and
``server.requests`` lists the paths asked for.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer


@dataclass
class FileServer:
    """A running file server: its port, files and the paths requested."""

    port: int
    files: dict[str, bytes]
    requests: list[str] = field(default_factory=list)

    def url(self, path: str) -> str:
        """The URL of ``path`` on this server."""
        return f"http://127.0.0.1:{self.port}{path}"


@contextmanager
def serving_files(files: dict[str, bytes]) -> Iterator[FileServer]:
    """Serve ``files`` (path -> bytes) on 127.0.0.1 until the block ends."""
    state = FileServer(port=0, files=dict(files))

    class Handler(BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            state.requests.append(self.path)
            content = state.files.get(self.path)
            if content is None:
                self.send_error(404)
                return
            self.send_response(200)
            self.send_header("Content-Type", "application/octet-stream")
            self.send_header("Content-Length", str(len(content)))
            self.end_headers()
            self.wfile.write(content)

        def log_message(self, format: str, *args: object) -> None:
            return

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    state.port = int(server.server_address[1])
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield state
    finally:
        server.shutdown()
        server.server_close()
        thread.join(timeout=5)
