"""Fixtures for schedule tests: a fresh app per test (the tick runs every schedule of its
database, so tests that move the clock must not share one), a writer, and the events spy."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from app.services.schedules import runs as schedule_runs
from tests.helpers.server import MAX_UPLOAD_BYTES, ApiServer, fresh_api


@pytest.fixture
def drop_root(tmp_path: Path) -> Path:
    """The directory root the operator allowed for directory sources."""
    root = tmp_path / "drop"
    root.mkdir()
    return root


@pytest.fixture
def api(tmp_path_factory: pytest.TempPathFactory, drop_root: Path) -> Iterator[ApiServer]:
    """The app on a fresh data directory, directory sources allowed under ``drop_root``."""
    yield from fresh_api(
        tmp_path_factory,
        "schedules-data",
        max_upload_bytes=MAX_UPLOAD_BYTES,
        schedule_directory_roots=[drop_root],
    )


@pytest.fixture
def writer(api: ApiServer) -> httpx.Client:
    """A writer of a fresh organisation."""
    return api.client(api.token("writer"))


@pytest.fixture
def events(monkeypatch: pytest.MonkeyPatch) -> list[dict[str, Any]]:
    """Every event the schedule runs publish (they still go through ``publish_event``)."""
    published: list[dict[str, Any]] = []
    real_publish = schedule_runs.publish_event

    def spy(
        session: Any, *, organisation_id: str, event_type: str, payload: dict[str, Any]
    ) -> None:
        published.append({"type": event_type, "organisation_id": organisation_id, **payload})
        real_publish(
            session, organisation_id=organisation_id, event_type=event_type, payload=payload
        )

    monkeypatch.setattr(schedule_runs, "publish_event", spy)
    return published
