"""A synthetic site's history through the real service (``scandiff serve``, real workers, the
real pipeline): a bin that moves on every rescan raises an alarm each time; once reviewers have
marked five of them false alarms the site learns its threshold, the bin stops firing, and a
crate left in the room still fires.  Every result states the site calibration it used."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import httpx
import pytest

from app.core.datasets.site import SiteVisit, site_visit
from app.db.models import JobStatus
from app.testing.files import ply_bytes
from app.testing.service import ServiceProcess
from tests.helpers.http import create_site, upload

ServiceFactory = Callable[..., ServiceProcess]
N_POINTS = 20_000
REFERENCE_BIN_SPOT = 5
LEARNING_BIN_SPOTS = (0, 1, 4, 6, 7)


def upload_visit(client: httpx.Client, site_id: str, visit: SiteVisit, **query: Any) -> dict:
    """Upload one visit with its sensor origin; the answer."""
    origin = ",".join(f"{value:.6f}" for value in visit.sensor_origin)
    response = upload(
        client,
        site_id,
        ply_bytes(visit.points),
        sensor_origin=origin,
        filename="visit.ply",
        **query,
    )
    assert response.status_code in (201, 202), response.text
    return response.json()


def compared(service: ServiceProcess, client: httpx.Client, site_id: str, visit: SiteVisit) -> dict:
    """Upload a visit and wait for its comparison; the succeeded job."""
    job = service.wait_for_job(
        client, upload_visit(client, site_id, visit)["job"]["id"], timeout=180
    )
    assert job["status"] == JobStatus.SUCCEEDED, job
    return job


def decisive(job: dict) -> dict:
    """The region test that decided the job."""
    (test,) = job["calibration"]["decision"]["tests"]
    assert test["statistic"] == "largest_region_extent_m"
    return test


@pytest.mark.slow  # seven real comparisons of 20k-point visits; make test keeps the parts:
# tests/api/test_verdicts.py (learning over the API), tests/core/test_site_calibration.py
def test_a_site_learns_to_ignore_its_recurring_false_alarm(service_factory: ServiceFactory) -> None:
    service = service_factory(workers=1)
    client = service.client()
    site = create_site(client, detector={"method": "pca", "variant": "improved", "params": {}})
    reference = site_visit(
        bin_spot=REFERENCE_BIN_SPOT, n_points=N_POINTS, sensor_shift=0.0, random_state=100
    )
    upload_visit(client, site["id"], reference, reference="true")

    learning_jobs = []
    for index, spot in enumerate(LEARNING_BIN_SPOTS):
        visit = site_visit(bin_spot=spot, n_points=N_POINTS, sensor_shift=0.5, random_state=index)
        job = compared(service, client, site["id"], visit)
        # before the site has learned anything the moved bin is an alarm
        assert job["changed"] is True and job["n_regions"] >= 1, job
        assert job["calibration"]["site"]["applied"] is False
        assert decisive(job)["source"] == "default"
        response = client.post(
            f"/api/v1/jobs/{job['id']}/verdict",
            json={"verdict": "false_alarm", "note": "the bin again"},
        )
        assert response.status_code == 200, response.text
        learning_jobs.append(job)
    calibration = client.get(f"/api/v1/sites/{site['id']}").json()["calibration"]
    assert calibration["status"] == "learned" and calibration["n_samples"] == 5
    assert sorted(calibration["source_job_ids"]) == sorted(job["id"] for job in learning_jobs)
    learned = calibration["thresholds"]["largest_region_extent_m"]
    assert learned == pytest.approx(max(decisive(job)["value"] for job in learning_jobs))

    # the same nuisance again: a region is still found, but it no longer decides "changed"
    again = compared(
        service,
        client,
        site["id"],
        site_visit(bin_spot=1, n_points=N_POINTS, sensor_shift=0.6, random_state=50),
    )
    assert again["n_regions"] >= 1 and again["changed"] is False, decisive(again)
    test = decisive(again)
    assert (test["source"], test["comparison"]) == ("site", ">")
    assert test["threshold"] == pytest.approx(learned) and 0 < test["value"] <= learned
    site_provenance = again["calibration"]["site"]
    assert site_provenance["applied"] is True and site_provenance["n_samples"] == 5
    assert site_provenance["rule"] == calibration["rule"]

    # a real change (a 1 m crate) still fires
    crate = compared(
        service,
        client,
        site["id"],
        site_visit(bin_spot=4, crate_spot=2, n_points=N_POINTS, sensor_shift=0.5, random_state=51),
    )
    assert crate["changed"] is True, decisive(crate)
    assert decisive(crate)["source"] == "site" and decisive(crate)["value"] > learned

    # the timeline lists the verdicts with the jobs
    items = client.get(f"/api/v1/sites/{site['id']}/jobs", params={"limit": 50}).json()["items"]
    verdicts = {item["id"]: (item["verdict"] or {}).get("verdict") for item in items}
    assert [verdicts[job["id"]] for job in learning_jobs] == ["false_alarm"] * 5
    assert verdicts[again["id"]] is None and verdicts[crate["id"]] is None
