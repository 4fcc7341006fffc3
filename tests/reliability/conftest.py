"""A server for the reliability tests: the real app (uvicorn in a thread, migrated SQLite file)
with a 1 MB upload cap (so bombs and oversize bodies stay cheap to send) and the default point
limit (so the readers' own bomb checks are what answers)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.helpers.server import RELIABILITY_MAX_UPLOAD_BYTES, ApiServer, fresh_api


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ApiServer]:
    """The app on a fresh data directory, for one test module."""
    yield from fresh_api(
        tmp_path_factory, "reliability-data", max_upload_bytes=RELIABILITY_MAX_UPLOAD_BYTES
    )
