"""A job a reviewer can trust at a glance, over HTTP: its explanation, quality warnings and
sensor origins, whether a failed job will retry, and the paper's detector names as aliases."""

from __future__ import annotations

import json

import httpx
import pytest

from app.core.pipeline import RegionSummary
from app.core.quality import LOW_FITNESS
from app.jobs.alerts.site_history import (
    HISTORY_MIN_JOBS,
    REGION_COUNT_MIN_EXCESS,
    RegionCountWarning,
)
from app.jobs.leases import claim_job, fail_job, make_lease_owner, release_job
from app.services.messages import API_FIXES
from app.testing.files import ply_bytes
from app.testing.results import calibration_report, registration_report, sensor_origin_entries
from app.testing.scenes import room_points
from tests.helpers.http import assert_error, create_site, site_with_reference, upload
from tests.helpers.jobs import finish_job, load_job
from tests.helpers.server import ApiServer

N_POINTS = 2000


def queued_scan_job(client: httpx.Client, site_id: str, seed: int, **query: str) -> dict:
    """Upload a scan to a site with a reference; its queued job (no consumer runs here)."""
    response = upload(client, site_id, ply_bytes(room_points(N_POINTS, seed=seed)), **query)
    assert response.status_code == 202, response.text
    return response.json()["job"]


def regions(count: int) -> list[RegionSummary]:
    """``count`` small added regions, the first the largest."""
    return [
        RegionSummary(
            "added", 300 - index, [1.0, 1.0, 0.5], [0.5, 0.5, 0.0], [1.5, 1.25, 1.0], 0.2, 0.3
        )
        for index in range(count)
    ]


def test_a_succeeded_job_explains_itself_and_carries_warnings_and_origins(
    api: ApiServer, writer: httpx.Client
) -> None:
    site, reference = site_with_reference(writer)
    job = queued_scan_job(writer, site["id"], seed=3)
    assert job["warnings"] is None and job["explanation"] is None and job["will_retry"] is False
    origins = {
        "reference": [{"origin": [1.0, 2.0, 1.2], "source": "given", "confidence": None}],
        "scan": [],
    }
    finish_job(
        api,
        job["id"],
        reference["n_points"],
        N_POINTS,
        regions=regions(2),
        score=0.03698,
        threshold=0.04244,
        calibration=calibration_report(rule="regions", detector_changed=False),
        localisation={"min_region_points": 200},
        registration=registration_report(
            fitness=LOW_FITNESS / 2,
            rotation_degrees=4.1,
            translation_m=0.1,
            max_correspondence_distance=0.3,
        ),
        sensor_origins=sensor_origin_entries(origins),
        warnings=["the scan's file sensor origin [0.0, 0.0, 0.0] is 3.1 m from ..."],
    )
    read = writer.get(f"/api/v1/jobs/{job['id']}").json()
    assert read["status"] == "succeeded" and read["will_retry"] is False
    assert read["sensor_origins"] == origins
    explanation = read["explanation"]
    assert explanation["decision"] == "changed" and explanation["decided_by"] == "regions"
    assert explanation["n_regions"] == 2 and explanation["n_region_points"] == 300 + 299
    assert explanation["text"].startswith("changed: 2 regions of 599 points (>= 200 each)")
    assert "score 0.037 is below its threshold 0.0424" in explanation["text"]
    codes = [warning["code"] for warning in read["warnings"]]
    assert codes == [
        "low_registration_fitness",
        "large_rotation",
        "sensor_origin",
        "sensor_origin_unknown",
    ]
    assert all(warning["message"] for warning in read["warnings"])
    assert read["warnings"][3]["side"] == "scan"
    # the site's job list carries them too (the dashboard's badges)
    listed = writer.get(f"/api/v1/sites/{site['id']}/jobs").json()["items"]
    assert [item["warnings"] for item in listed if item["id"] == job["id"]] == [read["warnings"]]


def test_a_region_count_far_above_the_sites_history_is_warned(
    api: ApiServer, writer: httpx.Client
) -> None:
    site, reference = site_with_reference(writer)
    usual = 2
    for seed in range(HISTORY_MIN_JOBS):
        job = queued_scan_job(writer, site["id"], seed=10 + seed)
        finish_job(api, job["id"], reference["n_points"], N_POINTS, regions=regions(usual))
        read = writer.get(f"/api/v1/jobs/{job['id']}").json()
        assert read["warnings"] == [], "no history yet, and a usual count"
    many = usual * 3 + REGION_COUNT_MIN_EXCESS + 1
    job = queued_scan_job(writer, site["id"], seed=20)
    finish_job(api, job["id"], reference["n_points"], N_POINTS, regions=regions(many))
    (warning,) = writer.get(f"/api/v1/jobs/{job['id']}").json()["warnings"]
    assert warning["code"] == "region_count_above_history"
    assert warning["value"] == many and warning["median"] == usual
    assert warning["history_jobs"] == HISTORY_MIN_JOBS
    assert f"{many} regions, far above this site's usual {usual}" in warning["message"]
    # stored as its typed form's JSON; the API adds only its own words for the fix
    (stored,) = load_job(api.settings, job["id"]).warnings
    limit = float(usual + REGION_COUNT_MIN_EXCESS)
    expected = RegionCountWarning(many, limit, float(usual), HISTORY_MIN_JOBS).to_json_dict()
    assert json.dumps(stored) == json.dumps(expected)
    text, parameters = API_FIXES["check_site_history"]
    expected["how_to_fix"].update(text=text, parameters=parameters)
    assert json.dumps(warning) == json.dumps(expected)
    # another site's history is its own: the same count there is not warned
    other, other_reference = site_with_reference(writer)
    job = queued_scan_job(writer, other["id"], seed=21)
    finish_job(api, job["id"], other_reference["n_points"], N_POINTS, regions=regions(many))
    assert writer.get(f"/api/v1/jobs/{job['id']}").json()["warnings"] == []


def test_a_failed_job_says_whether_it_will_retry(api: ApiServer, writer: httpx.Client) -> None:
    site, _ = site_with_reference(writer)
    job = queued_scan_job(writer, site["id"], seed=4)
    assert job["max_attempts"] > 1
    claimed = claim_job(job["id"], api.settings, make_lease_owner())
    assert claimed is not None
    assert release_job(claimed, api.settings, "worker crashed", count_attempt=True) == "queued"
    read = writer.get(f"/api/v1/jobs/{job['id']}").json()
    assert (read["status"], read["error"], read["will_retry"]) == ("queued", "worker crashed", True)
    claimed = claim_job(job["id"], api.settings, make_lease_owner())
    assert claimed is not None
    assert fail_job(claimed, api.settings, "the scan has no points")
    read = writer.get(f"/api/v1/jobs/{job['id']}").json()
    assert read["status"] == "failed" and read["attempts"] < read["max_attempts"]
    assert read["will_retry"] is False


@pytest.mark.parametrize(
    ("alias", "canonical"), [("PE-EMD", "planes"), ("pe", "planes"), ("Pca-Emd", "pca")]
)
def test_the_papers_names_create_sites_with_the_canonical_method(
    writer: httpx.Client, alias: str, canonical: str
) -> None:
    site = create_site(writer, detector={"method": alias, "variant": "paper"})
    assert site["detector"]["method"] == canonical
    assert writer.get(f"/api/v1/sites/{site['id']}").json()["detector"]["method"] == canonical
    updated = writer.patch(
        f"/api/v1/sites/{site['id']}", json={"detector": {"method": "GMM-EMD", "variant": "paper"}}
    )
    assert updated.status_code == 200, updated.text
    assert updated.json()["detector"]["method"] == "gmm"


def test_the_papers_names_work_for_jobs_and_uploads(writer: httpx.Client) -> None:
    site, reference = site_with_reference(writer)
    job = queued_scan_job(writer, site["id"], seed=5, method="pe-emd")
    assert job["method"] == "planes"
    created = writer.post(
        "/api/v1/jobs",
        json={"reference_scan_id": reference["id"], "scan_id": job["scan_id"], "method": "PCA-EMD"},
    )
    assert created.status_code == 202, created.text
    assert created.json()["method"] == "pca"
    detail = assert_error(
        writer.post(
            "/api/v1/jobs",
            json={"reference_scan_id": reference["id"], "scan_id": job["scan_id"], "method": "pe2"},
        ),
        422,
        "invalid_detector",
    )
    assert "pe2" in detail and "pe-emd" in detail
