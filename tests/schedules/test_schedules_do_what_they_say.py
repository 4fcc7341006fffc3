"""Schedules that do what they say (issue 31): the schedule's own detector, "run now" that
compares at once or says why not, ``schedule.missed`` once per missed spell, event bodies that
name the site, and a detector given by its method alone."""

from __future__ import annotations

from datetime import timedelta
from typing import Any

import httpx

from app.services.schedules.runs import tick
from app.testing.files import room_ply
from tests.helpers.http import site_with_reference, upload_accepted
from tests.helpers.schedules import created, new_schedule, runs_of
from tests.helpers.server import ApiServer


def run_now(client: httpx.Client, schedule_id: str) -> dict[str, Any]:
    """``POST /schedules/{id}/run``, asserting 201; the run."""
    response = client.post(f"/api/v1/schedules/{schedule_id}/run")
    assert response.status_code == 201, response.text
    return response.json()


def test_a_run_uses_the_schedules_detector_not_any_job_of_the_pair(
    api: ApiServer, writer: httpx.Client
) -> None:
    site, _reference = site_with_reference(writer)
    # the upload's own job runs PCA; the schedule asks for plane evidence with a parameter
    upload = upload_accepted(writer, site["id"], "night.ply", room_ply(5, with_box=True))
    detector = {"method": "planes", "variant": "paper", "params": {}}
    schedule = new_schedule(writer, site["id"], detector=detector)
    run = run_now(writer, schedule["id"])
    assert run["status"] == "compared", run
    assert run["scan_id"] == upload["scan"]["id"]
    assert run["job_id"] != upload["job"]["id"]
    job = writer.get(f"/api/v1/jobs/{run['job_id']}").json()
    assert (job["method"], job["variant"]) == ("planes", "paper")
    # the same detector again: that job is reused, not duplicated
    assert run_now(writer, schedule["id"])["job_id"] == run["job_id"]
    # a schedule with the upload's detector reuses the upload's job
    same = new_schedule(writer, site["id"], detector={"method": "pca"})
    assert run_now(writer, same["id"])["job_id"] == upload["job"]["id"]


def test_run_now_compares_a_scan_older_than_the_schedule_at_once(
    api: ApiServer, writer: httpx.Client
) -> None:
    site, reference = site_with_reference(writer)
    upload = upload_accepted(writer, site["id"], "night.ply", room_ply(5, with_box=True))
    schedule = new_schedule(writer, site["id"], detector={"method": "pca"})  # after the scan
    run = run_now(writer, schedule["id"])
    assert run["status"] == "compared", run
    assert run["scan_id"] == upload["scan"]["id"]
    assert run["reason"] is None
    job = writer.get(f"/api/v1/jobs/{run['job_id']}").json()
    assert (job["reference_scan_id"], job["scan_id"]) == (reference["id"], upload["scan"]["id"])


def test_run_now_with_nothing_to_compare_says_why(api: ApiServer, writer: httpx.Client) -> None:
    site, _reference = site_with_reference(writer)
    schedule = new_schedule(writer, site["id"])
    run = run_now(writer, schedule["id"])
    assert run["status"] == "missed"
    assert run["job_id"] is None
    assert site["name"] in run["reason"]
    assert f"POST /api/v1/sites/{site['id']}/scans" in run["reason"]
    assert runs_of(writer, schedule["id"])[0]["reason"] == run["reason"]


def test_schedule_missed_is_sent_once_per_missed_spell_and_names_the_site(
    api: ApiServer, writer: httpx.Client, events: list[dict[str, Any]]
) -> None:
    site, _reference = site_with_reference(writer)
    schedule = new_schedule(
        writer, site["id"], interval_seconds=60, catch_up="each", detector={"method": "pca"}
    )
    start = created(schedule)
    for minute in range(1, 11):  # ten one-minute periods without a scan, ticked on time
        tick(api.settings, start + timedelta(seconds=60 * minute + 2))
    runs = runs_of(writer, schedule["id"])
    assert [run["status"] for run in runs] == ["missed"] * 10
    assert all("no scan of site" in run["reason"] for run in runs)

    def missed_events() -> list[dict[str, Any]]:
        return [event for event in events if event["type"] == "schedule.missed"]

    assert [event["run_id"] for event in missed_events()] == [runs[0]["id"]]
    assert missed_events()[0]["site"] == {"id": site["id"], "name": site["name"]}
    assert writer.get(f"/api/v1/schedules/{schedule['id']}").json()["missed_since"] is not None
    # a scan arrives and is compared: the spell ends; the next silence is a new spell
    upload_accepted(writer, site["id"], "back.ply", room_ply(7))
    assert run_now(writer, schedule["id"])["status"] == "compared"
    assert writer.get(f"/api/v1/schedules/{schedule['id']}").json()["missed_since"] is None
    tick(api.settings, start + timedelta(seconds=60 * 11 + 2))
    tick(api.settings, start + timedelta(seconds=60 * 12 + 2))
    assert [run["status"] for run in runs_of(writer, schedule["id"])][-2:] == ["missed"] * 2
    assert len(missed_events()) == 2


def test_site_stale_names_the_site(
    api: ApiServer, writer: httpx.Client, events: list[dict[str, Any]]
) -> None:
    site, _reference = site_with_reference(writer)
    schedule = new_schedule(writer, site["id"], interval_seconds=3600, stale_after_seconds=60)
    tick(api.settings, created(schedule) + timedelta(seconds=3605))
    (stale,) = [event for event in events if event["type"] == "site.stale"]
    assert stale["site"] == {"id": site["id"], "name": site["name"]}


def test_a_detector_given_by_its_method_alone_gets_the_improved_variant(
    writer: httpx.Client,
) -> None:
    site = writer.post("/api/v1/sites", json={"name": "yard", "detector": {"method": "pe"}})
    assert site.status_code == 201, site.text
    assert site.json()["detector"] == {"method": "planes", "variant": "improved", "params": {}}
    schedule = new_schedule(writer, site.json()["id"], detector={"method": "pe"})
    assert schedule["detector"]["variant"] == "improved"
    patched = writer.patch(
        f"/api/v1/sites/{site.json()['id']}", json={"detector": {"method": "pca"}}
    )
    assert patched.status_code == 200, patched.text
    assert patched.json()["detector"]["variant"] == "improved"


def test_a_wrong_method_is_named_as_the_error(writer: httpx.Client) -> None:
    site = writer.post("/api/v1/sites", json={"name": "dock", "detector": {"method": "emd"}})
    assert site.status_code == 422, site.text
    detail = site.json()["detail"]
    assert "'emd'" in detail and "variant" not in detail
    for valid in ("gmm", "pca", "planes", "pe-emd"):
        assert valid in detail
    site_id = writer.post("/api/v1/sites", json={"name": "dock"}).json()["id"]
    schedule = writer.post(
        f"/api/v1/sites/{site_id}/schedules",
        json={"interval_seconds": 600, "detector": {"method": "emd"}},
    )
    assert schedule.status_code == 422, schedule.text
    assert "'emd'" in schedule.json()["detail"] and "variant" not in schedule.json()["detail"]
