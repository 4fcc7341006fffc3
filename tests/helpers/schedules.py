"""Schedules over HTTP: create one, read its runs."""

from __future__ import annotations

from datetime import datetime
from typing import Any

import httpx

from app.clock import as_utc


def new_schedule(client: httpx.Client, site_id: str, **body: Any) -> dict[str, Any]:
    """A new interval schedule (10 minutes unless ``body`` says otherwise), asserting 201."""
    body.setdefault("interval_seconds", 600)
    response = client.post(f"/api/v1/sites/{site_id}/schedules", json=body)
    assert response.status_code == 201, response.text
    return response.json()


def created(schedule: dict[str, Any]) -> datetime:
    """The schedule's creation time, the anchor of its periods."""
    return as_utc(datetime.fromisoformat(schedule["created_at"].replace("Z", "+00:00")))


def runs_of(client: httpx.Client, schedule_id: str) -> list[dict[str, Any]]:
    """Every run of a schedule, oldest period first."""
    response = client.get(f"/api/v1/schedules/{schedule_id}/runs", params={"limit": 200})
    assert response.status_code == 200, response.text
    return sorted(response.json()["items"], key=lambda run: run["period_start"])
