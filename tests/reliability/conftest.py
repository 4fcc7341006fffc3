"""A server for the reliability tests: the real app (uvicorn in a thread, migrated SQLite file)
with a 1 MB upload cap (so bombs and oversize bodies stay cheap to send) and the default point
limit (so the readers' own bomb checks are what answers)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from app.config import Settings
from tests.api.conftest import ApiServer, running_api

RELIABILITY_MAX_UPLOAD_BYTES = 1_000_000


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ApiServer]:
    """The app on a fresh data directory, for one test module."""
    settings = Settings(
        data_dir=tmp_path_factory.mktemp("reliability-data"),
        max_upload_bytes=RELIABILITY_MAX_UPLOAD_BYTES,
    )
    with running_api(settings) as handle:
        yield handle
