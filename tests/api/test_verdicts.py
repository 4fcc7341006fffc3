"""Review verdicts over HTTP: recorded with who and when, replaced with history kept,
``new_reference`` promoting the job's scan, only on succeeded jobs, bad input, tenancy, and the
site's calibration recomputed from its reviewed-null jobs."""

from __future__ import annotations

import httpx
import pytest

from app.core.pipeline import RegionSummary
from app.db.models import JobStatus, JobVerdict, ReferenceHistory
from app.testing.files import ply_bytes
from app.testing.scenes import room_points
from tests.helpers.database import count_rows
from tests.helpers.http import assert_error, site_with_reference, upload
from tests.helpers.jobs import finish_job
from tests.helpers.server import ApiServer

N_SCAN = 2000


def new_scan_job(client: httpx.Client, site_id: str, seed: int) -> dict:
    """Upload a scan; its (queued) job."""
    response = upload(client, site_id, ply_bytes(room_points(N_SCAN, seed=seed)))
    assert response.status_code == 202, response.text
    return response.json()["job"]


def finished_job(api: ApiServer, client: httpx.Client, site_id: str, seed: int, **kwargs) -> dict:
    """A scan's job, finished by playing the worker (one 12-point region)."""
    job = new_scan_job(client, site_id, seed)
    finish_job(api, job["id"], 3000, N_SCAN, **kwargs)
    return client.get(f"/api/v1/jobs/{job['id']}").json()


@pytest.fixture
def site_job(api: ApiServer, writer: httpx.Client) -> tuple[dict, dict, dict]:
    """A site, its reference and a succeeded job of it."""
    site, reference = site_with_reference(writer)
    return site, reference, finished_job(api, writer, site["id"], seed=11)


def test_verdict_is_recorded_with_who_and_when_and_replaced_with_history(
    api: ApiServer, writer: httpx.Client, site_job: tuple[dict, dict, dict]
) -> None:
    _site, _reference, job = site_job
    assert job["verdict"] is None
    response = writer.post(
        f"/api/v1/jobs/{job['id']}/verdict",
        json={"verdict": "confirmed", "note": "  the pallet was really moved  "},
    )
    assert response.status_code == 200, response.text
    verdict = response.json()["verdict"]
    assert (verdict["verdict"], verdict["note"]) == ("confirmed", "the pallet was really moved")
    assert verdict["set_by"]["role"] == "writer" and verdict["set_by"]["token_id"]
    assert verdict["set_at"] >= job["finished_at"]
    assert writer.get(f"/api/v1/jobs/{job['id']}").json()["verdict"] == verdict

    replaced = writer.post(f"/api/v1/jobs/{job['id']}/verdict", json={"verdict": "false_alarm"})
    assert replaced.status_code == 200, replaced.text
    assert replaced.json()["verdict"]["verdict"] == "false_alarm"
    assert replaced.json()["verdict"]["note"] is None
    history = writer.get(f"/api/v1/jobs/{job['id']}/verdicts").json()
    assert history["next_cursor"] is None
    assert [entry["verdict"] for entry in history["items"]] == ["false_alarm", "confirmed"]
    assert history["items"][1]["note"] == "the pallet was really moved"
    first_page = writer.get(f"/api/v1/jobs/{job['id']}/verdicts", params={"limit": 1}).json()
    assert [entry["verdict"] for entry in first_page["items"]] == ["false_alarm"]
    second_page = writer.get(
        f"/api/v1/jobs/{job['id']}/verdicts",
        params={"limit": 1, "cursor": first_page["next_cursor"]},
    ).json()
    assert [entry["verdict"] for entry in second_page["items"]] == ["confirmed"]
    assert second_page["next_cursor"] is None
    assert count_rows(api, JobVerdict, job_id=job["id"]) == 2
    # the job list (the timeline) carries the current verdict too
    listed = writer.get(f"/api/v1/sites/{job['site_id']}/jobs").json()["items"]
    assert [item["verdict"]["verdict"] for item in listed if item["id"] == job["id"]] == [
        "false_alarm"
    ]


def test_new_reference_makes_the_jobs_scan_the_reference_with_history(
    api: ApiServer, writer: httpx.Client, site_job: tuple[dict, dict, dict]
) -> None:
    site, reference, job = site_job
    assert count_rows(api, ReferenceHistory, site_id=site["id"]) == 1
    response = writer.post(f"/api/v1/jobs/{job['id']}/verdict", json={"verdict": "new_reference"})
    assert response.status_code == 200, response.text
    promoted = writer.get(f"/api/v1/sites/{site['id']}").json()
    assert promoted["reference_scan_id"] == job["scan_id"] != reference["id"]
    assert count_rows(api, ReferenceHistory, site_id=site["id"]) == 2
    # the next upload compares against the new reference
    assert new_scan_job(writer, site["id"], seed=12)["reference_scan_id"] == job["scan_id"]


def test_only_a_succeeded_job_gets_a_verdict(writer: httpx.Client) -> None:
    site, _reference = site_with_reference(writer)
    queued = new_scan_job(writer, site["id"], seed=13)
    assert queued["status"] == JobStatus.QUEUED
    detail = assert_error(
        writer.post(f"/api/v1/jobs/{queued['id']}/verdict", json={"verdict": "confirmed"}),
        409,
        "job_not_succeeded",
    )
    assert "queued" in detail and "succeeded" in detail


def test_bad_input_says_what_to_fix_and_other_organisations_jobs_are_404(
    api: ApiServer, writer: httpx.Client, site_job: tuple[dict, dict, dict]
) -> None:
    _site, _reference, job = site_job
    path = f"/api/v1/jobs/{job['id']}/verdict"
    detail = assert_error(writer.post(path, json={"verdict": "maybe"}), 422, "validation_error")
    assert "verdict" in detail and "false_alarm" in detail and "new_reference" in detail
    detail = assert_error(writer.post(path, json={"note": "no verdict"}), 422, "validation_error")
    assert "verdict" in detail
    assert_error(writer.post(path, json={"verdict": "confirmed", "by": "me"}), 422)
    assert_error(writer.post(path, json={"verdict": "confirmed", "note": "x" * 2001}), 422)
    assert_error(writer.post(path, content=b"not json"), 422)
    assert_error(
        writer.post(f"/api/v1/jobs/{'0' * 32}/verdict", json={"verdict": "confirmed"}), 404
    )
    stranger = api.client(api.token("writer"))
    assert_error(stranger.post(path, json={"verdict": "false_alarm"}), 404)
    assert_error(stranger.get(f"/api/v1/jobs/{job['id']}/verdicts"), 404)
    assert count_rows(api, JobVerdict, job_id=job["id"]) == 0


def test_a_reader_of_the_organisation_cannot_give_verdicts(
    api: ApiServer, writer: httpx.Client, site_job: tuple[dict, dict, dict]
) -> None:
    _site, _reference, job = site_job
    organisation = writer.get("/api/v1/organisation").json()["name"]
    reader = api.client(api.token("reader", organisation=organisation))
    assert reader.get(f"/api/v1/jobs/{job['id']}").status_code == 200
    assert_error(
        reader.post(f"/api/v1/jobs/{job['id']}/verdict", json={"verdict": "confirmed"}), 403
    )
    assert reader.get(f"/api/v1/jobs/{job['id']}/verdicts").json() == {
        "items": [],
        "next_cursor": None,
    }


def test_site_calibration_is_learned_from_reviewed_null_jobs(
    api: ApiServer, writer: httpx.Client
) -> None:
    site, _reference = site_with_reference(writer)
    # each job: a 12-point region of 1 x 1 x 1 m, and a wider one of fewer points, which is not
    # the largest region (the most points: what the Why line and the Review panel name)
    regions = [
        RegionSummary("added", 12, [1.0, 2.0, 0.5], [0.5, 1.5, 0.0], [1.5, 2.5, 1.0], 0.4, 0.9),
        RegionSummary("removed", 5, [2.0, 0.0, 0.0], [0.0, 0.0, 0.0], [4.0, 0.0, 0.0], 0.2, 0.3),
    ]
    changed_jobs = [
        finished_job(api, writer, site["id"], seed=20 + index, regions=regions)
        for index in range(5)
    ]
    unchanged_job = finished_job(api, writer, site["id"], seed=30, changed=False, regions=regions)

    def give(job: dict, verdict: str) -> dict:
        response = writer.post(f"/api/v1/jobs/{job['id']}/verdict", json={"verdict": verdict})
        assert response.status_code == 200, response.text
        return writer.get(f"/api/v1/sites/{site['id']}").json()["calibration"]

    for job in changed_jobs[:4]:
        calibration = give(job, "false_alarm")
    assert calibration["status"] == "learning" and calibration["n_samples"] == 4
    # confirmed on a job that said changed: a real change, not a calibration sample
    calibration = give(changed_jobs[4], "confirmed")
    assert calibration["status"] == "learning" and calibration["n_samples"] == 4
    # confirmed on a job that said unchanged: reviewed-unchanged, a sample
    calibration = give(unchanged_job, "confirmed")
    assert calibration["status"] == "learned" and calibration["n_samples"] == 5
    sources = [job["id"] for job in changed_jobs[:4]] + [unchanged_job["id"]]
    assert sorted(calibration["source_job_ids"]) == sorted(sources)
    assert calibration["rank"] == 5 and calibration["min_samples"] == 5
    assert calibration["false_alarm_rate"] == pytest.approx(api.settings.site_false_alarm_rate)
    # thresholds: the largest of the samples' statistics (rank 5 of 5); every finished job
    # has the same regions, the unchanged one too: the statistic is the 12-point region's size
    region = writer.get(f"/api/v1/jobs/{unchanged_job['id']}/regions").json()["items"][0]
    assert region["n_points"] == 12
    diagonal = sum(
        (high - low) ** 2 for low, high in zip(region["bbox_min"], region["bbox_max"], strict=True)
    )
    assert calibration["thresholds"]["largest_region_extent_m"] == pytest.approx(diagonal**0.5)
    assert calibration["thresholds"]["score"] == pytest.approx(changed_jobs[0]["score"])
    assert (calibration["method"], calibration["variant"]) == (
        site["detector"]["method"],
        site["detector"]["variant"],
    )
    # a verdict changed back to confirmed removes the sample again
    calibration = give(changed_jobs[0], "confirmed")
    assert calibration["status"] == "learning" and calibration["n_samples"] == 4


def test_a_new_detector_recomputes_the_site_calibration(
    api: ApiServer, writer: httpx.Client
) -> None:
    site, _reference = site_with_reference(writer)
    jobs = [finished_job(api, writer, site["id"], seed=40 + index) for index in range(5)]
    for job in jobs:
        response = writer.post(f"/api/v1/jobs/{job['id']}/verdict", json={"verdict": "false_alarm"})
        assert response.status_code == 200, response.text
    learned = writer.get(f"/api/v1/sites/{site['id']}").json()["calibration"]
    assert learned["status"] == "learned" and learned["method"] == site["detector"]["method"]

    def set_detector(detector: dict) -> dict:
        response = writer.patch(f"/api/v1/sites/{site['id']}", json={"detector": detector})
        assert response.status_code == 200, response.text
        return response.json()["calibration"]

    # the samples were the old detector's: under another one the site learns afresh
    other = set_detector({"method": "pca", "variant": "improved", "params": {}})
    assert other["status"] == "learning" and other["n_samples"] == 0
    assert (other["method"], other["variant"]) == ("pca", "improved")
    # back to the first detector: its reviewed jobs count again
    again = set_detector(site["detector"])
    assert again["status"] == "learned" and again["n_samples"] == 5
    assert again["thresholds"] == learned["thresholds"]
