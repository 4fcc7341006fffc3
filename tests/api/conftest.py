"""Fixtures for API tests: the real app served by uvicorn over HTTP on a migrated SQLite file.

``api`` is one server per test module (:func:`tests.helpers.server.fresh_api`); tests isolate
themselves by creating their own organisations and tokens (``api.token(...)``).  No job
consumer runs here: jobs stay ``queued`` unless a test plays the worker
(:func:`tests.helpers.jobs.finish_job`); the whole flow with a real consumer is in
``test_service_flow.py``.
"""

from __future__ import annotations

from collections.abc import Iterator

import httpx
import pytest

from tests.helpers.server import MAX_UPLOAD_BYTES, ApiServer, fresh_api


@pytest.fixture(scope="module")
def api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ApiServer]:
    """The app on a fresh, migrated data directory, for one test module."""
    yield from fresh_api(tmp_path_factory, "api-data", max_upload_bytes=MAX_UPLOAD_BYTES)


@pytest.fixture
def writer(api: ApiServer) -> httpx.Client:
    """A writer of a fresh organisation."""
    return api.client(api.token("writer"))
