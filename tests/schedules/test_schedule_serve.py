"""``scandiff serve`` schedules by itself: its job consumer ticks, no extra process runs."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from app.testing.files import room_ply
from app.testing.service import ServiceProcess
from app.testing.waiting import wait_until
from tests.helpers.http import site_with_reference, upload_accepted

FAST_SCHEDULES = {
    "SCANDIFF_SCHEDULE_TICK_SECONDS": "0.5",
    "SCANDIFF_SCHEDULE_MIN_INTERVAL_SECONDS": "1",
}


def test_serve_runs_due_periods_and_their_comparisons(
    service_factory: Callable[..., ServiceProcess],
) -> None:
    service = service_factory(workers=1, env=FAST_SCHEDULES)
    with service.client() as client:
        site, _reference = site_with_reference(client)
        upload_accepted(client, site["id"], "night.ply", room_ply(5, with_box=True))
        response = client.post(
            f"/api/v1/sites/{site['id']}/schedules",
            json={"interval_seconds": 2, "catch_up": "each", "stale_after_seconds": 3600},
        )
        assert response.status_code == 201, response.text
        schedule = response.json()

        def runs() -> list[dict[str, Any]]:
            page = client.get(f"/api/v1/schedules/{schedule['id']}/runs", params={"limit": 200})
            return list(page.json()["items"])

        # no scan arrived in the first period after creation: missed; then one that arrives runs
        wait_until(lambda: any(run["status"] == "missed" for run in runs()), 60, "a missed period")
        scan = upload_accepted(client, site["id"], "later.ply", room_ply(6))
        compared = wait_until(
            lambda: [run for run in runs() if run["status"] == "compared"], 60, "a compared period"
        )
        assert compared[0]["scan_id"] == scan["scan"]["id"]
        job = wait_until(
            lambda: (
                (body := client.get(f"/api/v1/jobs/{compared[0]['job_id']}").json())["status"]
                == "succeeded"
                and body
            ),
            120,
            "the compared period's job to finish",
        )
        assert job["scan_id"] == scan["scan"]["id"]
        periods = [run["period_start"] for run in runs()]
        assert len(periods) == len(set(periods))
