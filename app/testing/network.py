"""Network helpers: a free TCP port, one TLS context for local clients, whose token a server
knows."""

from __future__ import annotations

import socket
import ssl
from functools import cache

import httpx


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])


@cache
def local_tls_context() -> ssl.SSLContext:
    """One TLS context for every ``httpx.Client`` on a local plain-HTTP server.

    httpx builds a context for each client it is not given one (about 23 ms of CPU: it loads a
    CA bundle), so a test opening 400 clients spent 9 CPU s there; the servers of the tests
    and benchmarks speak plain HTTP, so the context never serves a handshake.
    """
    return ssl.create_default_context()


def token_status(base_url: str, token: str) -> int:
    """The status ``GET /api/v1/sites`` with ``token`` answers at ``base_url``: 200 from the
    server whose database holds the token, 401 or 403 from another server on that port."""
    return httpx.get(
        base_url + "/api/v1/sites",
        headers={"Authorization": f"Bearer {token}"},
        timeout=5.0,
        verify=local_tls_context(),
    ).status_code
