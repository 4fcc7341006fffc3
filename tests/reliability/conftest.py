"""A server for the reliability tests: the real app (uvicorn in a thread, migrated SQLite file)
with a 1 MB upload cap (so bombs and oversize bodies stay cheap to send) and the default point
limit (so the readers' own bomb checks are what answers)."""

from __future__ import annotations

import sqlite3
import time
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

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


def database_rows(data_dir: Path, table: str) -> list[dict[str, Any]]:
    """Every row of ``table`` in the SQLite file of a ``scandiff serve`` data directory.

    Read-only and outside the service's engine: in WAL mode a reader never waits for, nor
    blocks, the service's writers.
    """
    connection = sqlite3.connect(f"file:{data_dir / 'scandiff.sqlite3'}?mode=ro", uri=True)
    connection.row_factory = sqlite3.Row
    try:
        return [dict(row) for row in connection.execute(f"SELECT * FROM {table}")]
    finally:
        connection.close()


def job_status_counts(data_dir: Path) -> Counter[str]:
    """How many jobs of a ``scandiff serve`` data directory are in each status."""
    return Counter(job["status"] for job in database_rows(data_dir, "job"))


def wait_until(condition: Callable[[], bool], timeout: float, what: str) -> None:
    """Poll ``condition`` every 20 ms until it holds; TimeoutError naming ``what`` after."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError(f"not reached after {timeout} s: {what}")
        time.sleep(0.02)
