"""The organisation's job list (``GET /api/v1/jobs``) and the review inbox's counts
(``GET /api/v1/jobs/awaiting-review/counts``) over HTTP: filters by site, status, decision,
verdict (``none``: awaiting one) and creation time, newest first, paged by cursor, bad input
refused in words, and another organisation's jobs never listed or counted."""

from __future__ import annotations

from datetime import datetime
from typing import Any

import httpx
import pytest

from app.testing.files import ply_bytes
from app.testing.scenes import room_points
from tests.helpers.http import assert_error, site_with_reference, upload
from tests.helpers.jobs import finish_job
from tests.helpers.server import ApiServer

N_SCAN = 1500


def queued_job(client: httpx.Client, site_id: str, seed: int) -> dict[str, Any]:
    """Upload a scan to ``site_id``; its queued job."""
    response = upload(client, site_id, ply_bytes(room_points(N_SCAN, seed=seed)))
    assert response.status_code == 202, response.text
    return response.json()["job"]


def listed(client: httpx.Client, **query: Any) -> list[str]:
    """The ids of every job ``GET /jobs`` lists with ``query``, following the cursor."""
    ids: list[str] = []
    cursor = None
    while True:
        page_query = {**query, "cursor": cursor} if cursor else query
        response = client.get("/api/v1/jobs", params=page_query)
        assert response.status_code == 200, response.text
        page = response.json()
        ids += [job["id"] for job in page["items"]]
        cursor = page["next_cursor"]
        if cursor is None:
            return ids


@pytest.fixture(scope="module")
def fleet(api: ApiServer) -> dict[str, Any]:
    """Two sites of one organisation and five jobs, oldest first: A1 changed and confirmed,
    A2 unchanged, B1 changed (both awaiting a verdict), A3 and B2 queued."""
    client = api.client(api.token("writer"))
    site_a, reference_a = site_with_reference(client)
    site_b, reference_b = site_with_reference(client)
    jobs: dict[str, dict[str, Any]] = {}
    for name, site, reference, changed in (
        ("A1", site_a, reference_a, True),
        ("A2", site_a, reference_a, False),
        ("B1", site_b, reference_b, True),
        ("A3", site_a, reference_a, None),
        ("B2", site_b, reference_b, None),
    ):
        job = queued_job(client, site["id"], seed=len(jobs) + 20)
        if changed is not None:
            finish_job(api, job["id"], reference["n_points"], N_SCAN, changed=changed)
        jobs[name] = client.get(f"/api/v1/jobs/{job['id']}").json()
    answer = client.post(f"/api/v1/jobs/{jobs['A1']['id']}/verdict", json={"verdict": "confirmed"})
    assert answer.status_code == 200, answer.text
    return {"client": client, "site_a": site_a, "site_b": site_b, "jobs": jobs}


def ids_of(fleet: dict[str, Any], *names: str) -> list[str]:
    """The ids of the fleet's jobs ``names``."""
    return [fleet["jobs"][name]["id"] for name in names]


def test_the_job_list_is_the_organisations_jobs_newest_first(fleet: dict[str, Any]) -> None:
    client = fleet["client"]
    everything = listed(client)
    assert everything == ids_of(fleet, "B2", "A3", "B1", "A2", "A1")
    # pages of 2 give the same list, 3 pages
    first = client.get("/api/v1/jobs", params={"limit": 2}).json()
    assert [job["id"] for job in first["items"]] == everything[:2] and first["next_cursor"]
    assert listed(client, limit=2) == everything
    item = first["items"][0]
    assert item["scan_filename"] == "scan.ply" and item["site_id"] == fleet["site_b"]["id"]


def test_the_job_list_filters_by_site_status_decision_verdict_and_time(
    fleet: dict[str, Any],
) -> None:
    client = fleet["client"]
    site_a = fleet["site_a"]["id"]
    assert listed(client, site_id=site_a) == ids_of(fleet, "A3", "A2", "A1")
    assert listed(client, status="queued") == ids_of(fleet, "B2", "A3")
    assert listed(client, changed="true") == ids_of(fleet, "B1", "A1")
    assert listed(client, changed="false") == ids_of(fleet, "A2")
    assert listed(client, verdict="confirmed") == ids_of(fleet, "A1")
    assert listed(client, verdict="false_alarm") == []
    assert listed(client, status="succeeded", verdict="none") == ids_of(fleet, "B1", "A2")
    assert listed(client, status="succeeded", verdict="none", site_id=site_a) == ids_of(fleet, "A2")
    b1_created = fleet["jobs"]["B1"]["created_at"]
    assert listed(client, created_after=b1_created) == ids_of(fleet, "B2", "A3", "B1")
    assert listed(client, created_before=b1_created) == ids_of(fleet, "A2", "A1")
    assert listed(
        client, created_after=fleet["jobs"]["A2"]["created_at"], created_before=b1_created
    ) == ids_of(fleet, "A2")


def test_the_inbox_counts_jobs_awaiting_a_verdict_per_site(
    api: ApiServer, fleet: dict[str, Any]
) -> None:
    client = fleet["client"]
    counts = client.get("/api/v1/jobs/awaiting-review/counts")
    assert counts.status_code == 200, counts.text
    body = counts.json()
    assert body["total"] == 2
    assert [(site["site_id"], site["site_name"], site["count"]) for site in body["sites"]] == [
        (fleet["site_b"]["id"], fleet["site_b"]["name"], 1),
        (fleet["site_a"]["id"], fleet["site_a"]["name"], 1),
    ]
    newest = [datetime.fromisoformat(site["newest_at"]) for site in body["sites"]]
    assert newest == [
        datetime.fromisoformat(fleet["jobs"][name]["created_at"]) for name in ("B1", "A2")
    ]
    # another organisation sees nothing of it
    stranger = api.client(api.token("reader"))
    assert stranger.get("/api/v1/jobs/awaiting-review/counts").json() == {"total": 0, "sites": []}
    assert stranger.get("/api/v1/jobs").json() == {"items": [], "next_cursor": None}


def test_a_verdict_takes_a_job_out_of_the_inbox(api: ApiServer) -> None:
    client = api.client(api.token("writer"))
    site, reference = site_with_reference(client)
    job = queued_job(client, site["id"], seed=40)
    finish_job(api, job["id"], reference["n_points"], N_SCAN)
    assert listed(client, verdict="none", status="succeeded") == [job["id"]]
    assert client.get("/api/v1/jobs/awaiting-review/counts").json()["total"] == 1
    answer = client.post(f"/api/v1/jobs/{job['id']}/verdict", json={"verdict": "false_alarm"})
    assert answer.status_code == 200, answer.text
    assert listed(client, verdict="none", status="succeeded") == []
    assert listed(client, verdict="false_alarm") == [job["id"]]
    assert client.get("/api/v1/jobs/awaiting-review/counts").json() == {"total": 0, "sites": []}


def test_bad_job_list_queries_are_refused_in_words(api: ApiServer, fleet: dict[str, Any]) -> None:
    client = fleet["client"]
    assert_error(client.get("/api/v1/jobs", params={"site_id": "0" * 32}), 404)
    stranger = api.client(api.token("writer"))
    assert_error(stranger.get("/api/v1/jobs", params={"site_id": fleet["site_a"]["id"]}), 404)
    detail = assert_error(client.get("/api/v1/jobs", params={"verdict": "maybe"}), 422)
    assert "none" in detail and "false_alarm" in detail
    detail = assert_error(client.get("/api/v1/jobs", params={"status": "done"}), 422)
    assert "succeeded" in detail
    assert_error(client.get("/api/v1/jobs", params={"changed": "perhaps"}), 422)
    assert_error(client.get("/api/v1/jobs", params={"created_after": "last tuesday"}), 422)
    assert_error(client.get("/api/v1/jobs", params={"limit": 0}), 422)
    assert_error(client.get("/api/v1/jobs", params={"limit": 201}), 422)
    assert_error(client.get("/api/v1/jobs", params={"cursor": "not-ours"}), 400, "bad_cursor")
    assert_error(httpx.get(f"{api.base_url}/api/v1/jobs"), 401)
