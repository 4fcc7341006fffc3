"""The real app served by uvicorn in a background thread on a migrated SQLite file.

:func:`fresh_api` runs ``create_app(Settings(data_dir=...))`` after ``upgrade_to_head`` on a
free port and yields an :class:`ApiServer`; tests isolate themselves by creating their own
organisations and tokens (``api.token(...)``).  No job consumer runs: jobs stay ``queued``
unless a test plays the worker (:func:`tests.helpers.jobs.finish_job`).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import pytest
import uvicorn

from app.config import Settings
from app.db.session import transaction
from app.main import create_app
from app.services.auth import create_token
from app.testing.network import free_port, local_tls_context
from tests.helpers.http import unique_name
from tests.helpers.migrated_database import install_migrated_database

MAX_UPLOAD_BYTES = 400_000
"""Upload cap of the API test server (a 5k-point binary PLY is ~60 kB; 413 tests send more)."""

RELIABILITY_MAX_UPLOAD_BYTES = 1_000_000
"""Upload cap of the reliability test server (bombs and oversize bodies stay cheap to send)."""


@dataclass
class ApiServer:
    """A running app and handles on its data."""

    settings: Settings
    base_url: str
    clients: list[httpx.Client] = field(default_factory=list)

    @property
    def data_dir(self) -> Path:
        """The server's data directory."""
        return self.settings.data_dir

    def token(self, role: str = "writer", organisation: str | None = None) -> str:
        """A new token for ``organisation`` (default: a fresh one)."""
        with transaction(self.settings.sqlalchemy_url) as session:
            return create_token(session, organisation or unique_name("org"), role)

    def client(self, token: str | None = None, **kwargs: Any) -> httpx.Client:
        """An HTTP client on the server, authenticated with ``token`` when given."""
        headers = dict(kwargs.pop("headers", {}))
        if token:
            headers["Authorization"] = f"Bearer {token}"
        kwargs.setdefault("verify", local_tls_context())  # one context, not one per client
        client = httpx.Client(base_url=self.base_url, headers=headers, timeout=30.0, **kwargs)
        self.clients.append(client)
        return client

    def stored_files(self) -> list[Path]:
        """Every file under scans/ and tmp/ (what uploads leave behind)."""
        return sorted(
            path
            for directory in (self.settings.scans_dir, self.settings.tmp_dir)
            for path in directory.rglob("*")
            if path.is_file()
        )


def start_server(settings: Settings) -> tuple[uvicorn.Server, threading.Thread, str]:
    """Migrate (a copy of the session's migrated file for a new SQLite database), then run
    uvicorn with ``create_app(settings)`` in a thread; wait until it serves."""
    install_migrated_database(settings.sqlalchemy_url)
    port = free_port()
    config = uvicorn.Config(
        create_app(settings), host="127.0.0.1", port=port, log_level="warning", lifespan="off"
    )
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 20
    while not server.started:
        if time.monotonic() > deadline or not thread.is_alive():
            raise RuntimeError("test server did not start")
        time.sleep(0.02)
    return server, thread, f"http://127.0.0.1:{port}"


@contextmanager
def running_api(settings: Settings) -> Iterator[ApiServer]:
    """The app served by uvicorn in a thread for ``settings``; stopped on exit."""
    server, thread, base_url = start_server(settings)
    handle = ApiServer(settings=settings, base_url=base_url)
    try:
        yield handle
    finally:
        for client in handle.clients:
            client.close()
        server.should_exit = True
        thread.join(timeout=10)


def fresh_api(
    tmp_path_factory: pytest.TempPathFactory, directory: str, **settings: Any
) -> Iterator[ApiServer]:
    """The app on a fresh data directory ``directory`` with ``settings``, until resumed.

    For module fixtures: ``yield from fresh_api(tmp_path_factory, "api-data", ...)``.
    """
    data_dir = tmp_path_factory.mktemp(directory)
    with running_api(Settings(data_dir=data_dir, **settings)) as handle:
        yield handle
