"""The test services' start survives a port another server took between choosing and binding.

``free_port`` returns a port that was free a moment ago; under ``make test``'s parallel
processes another test's server can take it before ``scandiff serve`` binds it.  Its health
check then answered 200 and the test's requests met that other server ("invalid or revoked
token").  A service now checks that the server on its port knows its admin token and moves to
a fresh port when it does not.
"""

from __future__ import annotations

import os
import sys
import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest

from app.testing.service import PortTakenError, ServiceProcess
from app.testing.topology import ApiProcess
from tests.helpers.http import create_site


class _ForeignServer(BaseHTTPRequestHandler):
    """Healthy to anyone, and refusing every token: another service."""

    def do_GET(self) -> None:
        healthy = self.path.endswith("/health")
        body = b'{"status": "ok"}' if healthy else b'{"error": "unauthorized"}'
        self.send_response(200 if healthy else 401)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args: object) -> None:
        """Quiet."""


@pytest.fixture
def foreign_port() -> Iterator[int]:
    """A port held by a server that is not the test's service."""
    server = ThreadingHTTPServer(("127.0.0.1", 0), _ForeignServer)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield int(server.server_address[1])
    server.shutdown()
    server.server_close()


def test_a_service_whose_port_was_taken_starts_on_another(tmp_path: Path, foreign_port: int):
    service = ServiceProcess(tmp_path / "service", workers=0)
    service.port = foreign_port  # the race: the chosen port is taken before serve binds it
    try:
        service.start()
        assert service.port != foreign_port
        with service.client() as client:
            assert create_site(client)["id"]
    finally:
        service.kill()


def test_a_service_given_a_taken_port_says_so(tmp_path: Path, foreign_port: int):
    service = ServiceProcess(tmp_path / "service", workers=0, port=foreign_port)
    try:
        with pytest.raises(PortTakenError, match=str(foreign_port)):
            service.start()
    finally:
        service.kill()


_TOKEN_SERVER = """
import sys
from http.server import BaseHTTPRequestHandler, HTTPServer

class Handler(BaseHTTPRequestHandler):
    def do_GET(self):
        ours = self.headers.get("Authorization") == "Bearer ours"
        status = 200 if self.path.endswith("/health") or ours else 401
        self.send_response(status)
        self.send_header("Content-Length", "0")
        self.end_headers()

try:
    HTTPServer(("127.0.0.1", int(sys.argv[sys.argv.index("--port") + 1])), Handler).serve_forever()
except OSError as error:
    print(f"error while attempting to bind: {error} address already in use", flush=True)
    sys.exit(1)
"""


def test_a_topology_api_refuses_a_foreign_server_as_its_health(tmp_path: Path, foreign_port: int):
    api = ApiProcess("api", [], {}, tmp_path / "api.log", port=foreign_port, admin_token="ours")
    assert not api.healthy()
    assert ApiProcess("api", [], {}, tmp_path / "api.log", port=foreign_port).healthy()


def test_a_topology_api_whose_port_was_taken_moves_to_a_fresh_port(
    tmp_path: Path, foreign_port: int
):
    command = [sys.executable, "-c", _TOKEN_SERVER, "--port", str(foreign_port)]
    api = ApiProcess(
        "api",
        command,
        dict(os.environ),
        tmp_path / "api.log",
        port=foreign_port,
        admin_token="ours",
    )
    try:
        api.start()
        assert api.port != foreign_port
        assert api.command[-1] == str(api.port)
        assert api.healthy()
    finally:
        api.kill()
