"""Schedules over HTTP: create, list, read, change, delete, tenancy and the 422s of bad input."""

from __future__ import annotations

from pathlib import Path

import httpx

from app.db.models import Schedule, ScheduleRun
from app.testing.files import room_ply
from tests.helpers.database import count_rows
from tests.helpers.http import assert_error, create_site, site_with_reference, upload_accepted
from tests.helpers.server import ApiServer

NIGHTLY = {"cron": "0 2 * * *", "timezone": "Europe/Lisbon"}


def create_schedule(client: httpx.Client, site_id: str, **body: object) -> httpx.Response:
    """POST a schedule of ``site_id``."""
    return client.post(f"/api/v1/sites/{site_id}/schedules", json=body)


def test_create_read_list_change_and_delete_a_schedule(writer: httpx.Client) -> None:
    site = create_site(writer)
    response = create_schedule(writer, site["id"], **NIGHTLY, stale_after_seconds=86400)
    assert response.status_code == 201, response.text
    schedule = response.json()
    assert schedule["source"] == "uploads"
    assert schedule["catch_up"] == "latest"
    assert schedule["compare_previous"] is False
    assert schedule["next_run_at"].endswith("Z")
    assert writer.get(f"/api/v1/schedules/{schedule['id']}").json() == schedule
    listed = writer.get(f"/api/v1/sites/{site['id']}/schedules").json()
    assert [item["id"] for item in listed] == [schedule["id"]]

    changed = writer.patch(
        f"/api/v1/schedules/{schedule['id']}",
        json={"cron": None, "interval_seconds": 3600, "catch_up": "each", "compare_previous": True},
    )
    assert changed.status_code == 200, changed.text
    assert changed.json()["interval_seconds"] == 3600
    assert changed.json()["cron"] is None
    assert changed.json()["catch_up"] == "each"

    runs = writer.get(f"/api/v1/schedules/{schedule['id']}/runs")
    assert runs.status_code == 200
    assert runs.json() == {"items": [], "next_cursor": None}

    assert writer.delete(f"/api/v1/schedules/{schedule['id']}").status_code == 204
    assert_error(writer.get(f"/api/v1/schedules/{schedule['id']}"), 404, "not_found")
    assert writer.get(f"/api/v1/sites/{site['id']}/schedules").json() == []


def test_a_schedule_with_a_detector_and_a_bad_detector(writer: httpx.Client) -> None:
    site = create_site(writer)
    detector = {"method": "pca", "variant": "paper", "params": {}}
    response = create_schedule(writer, site["id"], **NIGHTLY, detector=detector)
    assert response.status_code == 201, response.text
    assert response.json()["detector"] == detector
    bad = {"method": "magic", "variant": "x", "params": {}}
    detail = assert_error(
        create_schedule(writer, site["id"], **NIGHTLY, detector=bad), 422, "invalid_detector"
    )
    assert "magic" in detail


def test_bad_rhythms_and_zones_are_422_saying_what_to_fix(writer: httpx.Client) -> None:
    site_id = create_site(writer)["id"]
    detail = assert_error(create_schedule(writer, site_id, cron="61 * * * *"), 422, "invalid_cron")
    assert "five fields" in detail
    assert_error(create_schedule(writer, site_id, cron="every night"), 422, "invalid_cron")
    detail = assert_error(create_schedule(writer, site_id, cron="* * * * * *"), 422, "invalid_cron")
    assert "no seconds field" in detail
    detail = assert_error(
        create_schedule(writer, site_id, cron="0 2 * * *", timezone="Mars/Olympus"),
        422,
        "invalid_timezone",
    )
    assert "Europe/Lisbon" in detail
    assert_error(
        create_schedule(writer, site_id, cron="0 2 * * *", timezone="../../etc/passwd"), 422
    )
    detail = assert_error(
        create_schedule(writer, site_id, cron="0 2 * * *", interval_seconds=3600),
        422,
        "invalid_rhythm",
    )
    assert "both" in detail
    detail = assert_error(create_schedule(writer, site_id), 422, "invalid_rhythm")
    assert "neither" in detail
    detail = assert_error(
        create_schedule(writer, site_id, interval_seconds=30), 422, "invalid_rhythm"
    )
    assert "at least 60" in detail
    assert_error(create_schedule(writer, site_id, **NIGHTLY, catch_up="sometimes"), 422)
    assert_error(create_schedule(writer, site_id, **NIGHTLY, colour="red"), 422)
    schedule = create_schedule(writer, site_id, **NIGHTLY).json()
    assert_error(
        writer.patch(f"/api/v1/schedules/{schedule['id']}", json={"interval_seconds": 600}),
        422,
        "invalid_rhythm",
    )
    assert_error(
        writer.patch(f"/api/v1/schedules/{schedule['id']}", json={"timezone": "Nowhere"}),
        422,
        "invalid_timezone",
    )
    assert writer.get(f"/api/v1/schedules/{schedule['id']}").json() == schedule


def test_bad_sources_are_422(writer: httpx.Client, drop_root: Path, tmp_path: Path) -> None:
    site_id = create_site(writer)["id"]
    detail = assert_error(
        create_schedule(writer, site_id, **NIGHTLY, source={"url": "ftp://example.com/a.ply"}),
        422,
        "invalid_url",
    )
    assert "http" in detail
    assert_error(
        create_schedule(writer, site_id, **NIGHTLY, source={"url": "file:///etc/passwd"}),
        422,
        "invalid_url",
    )
    for address in ("127.0.0.1", "10.1.2.3", "169.254.169.254", "[::1]", "192.168.0.10"):
        detail = assert_error(
            create_schedule(
                writer, site_id, **NIGHTLY, source={"url": f"http://{address}:8080/scan.ply"}
            ),
            422,
            "forbidden_url_address",
        )
        assert "SCANDIFF_ALLOW_PRIVATE_ADDRESSES" in detail
    outside = tmp_path / "outside"
    outside.mkdir()
    assert_error(
        create_schedule(writer, site_id, **NIGHTLY, source={"directory": str(outside)}),
        422,
        "directory_not_allowed",
    )
    assert_error(create_schedule(writer, site_id, **NIGHTLY, source={"bucket": "s3://x"}), 422)


def test_other_organisations_and_unknown_ids_are_404(api: ApiServer, writer: httpx.Client) -> None:
    site, _reference = site_with_reference(writer)
    schedule = create_schedule(writer, site["id"], **NIGHTLY).json()
    other = api.client(api.token("writer"))
    for method, path in (
        ("GET", f"/api/v1/schedules/{schedule['id']}"),
        ("PATCH", f"/api/v1/schedules/{schedule['id']}"),
        ("DELETE", f"/api/v1/schedules/{schedule['id']}"),
        ("POST", f"/api/v1/schedules/{schedule['id']}/run"),
        ("GET", f"/api/v1/schedules/{schedule['id']}/runs"),
        ("GET", f"/api/v1/sites/{site['id']}/schedules"),
        ("POST", f"/api/v1/sites/{site['id']}/schedules"),
        ("GET", "/api/v1/schedules/" + "0" * 32),
    ):
        body = {} if method == "PATCH" else NIGHTLY if method == "POST" else None
        response = other.request(method, path, json=body)
        assert_error(response, 404, "not_found")
    assert count_rows(api, ScheduleRun) == 0
    assert writer.get(f"/api/v1/schedules/{schedule['id']}").status_code == 200


def test_readers_read_but_do_not_write(api: ApiServer, writer: httpx.Client) -> None:
    site = create_site(writer)
    schedule = create_schedule(writer, site["id"], **NIGHTLY).json()
    reader = api.client(api.token("reader", organisation=None))
    assert reader.get(f"/api/v1/schedules/{schedule['id']}").status_code == 404
    org_reader_token = api.token("reader", organisation=organisation_of(api, writer))
    org_reader = api.client(org_reader_token)
    assert org_reader.get(f"/api/v1/schedules/{schedule['id']}").status_code == 200
    assert_error(create_schedule(org_reader, site["id"], **NIGHTLY), 403)
    assert_error(org_reader.post(f"/api/v1/schedules/{schedule['id']}/run"), 403)
    assert_error(org_reader.delete(f"/api/v1/schedules/{schedule['id']}"), 403)


def organisation_of(api: ApiServer, client: httpx.Client) -> str:
    """The organisation name of ``client``'s token."""
    response = client.get("/api/v1/organisation")
    assert response.status_code == 200, response.text
    return str(response.json()["name"])


def test_deleting_a_site_deletes_its_schedules_and_runs(
    api: ApiServer, writer: httpx.Client
) -> None:
    site, _reference = site_with_reference(writer)
    schedule = create_schedule(writer, site["id"], **NIGHTLY).json()
    upload_accepted(writer, site["id"], "night.ply", room_ply(5, with_box=True))
    run = writer.post(f"/api/v1/schedules/{schedule['id']}/run")
    assert run.status_code == 201, run.text
    assert run.json()["status"] == "compared"
    assert writer.delete(f"/api/v1/sites/{site['id']}").status_code == 204
    assert_error(writer.get(f"/api/v1/schedules/{schedule['id']}"), 404)
    assert count_rows(api, Schedule, site_id=site["id"]) == 0
    assert count_rows(api, ScheduleRun, schedule_id=schedule["id"]) == 0
