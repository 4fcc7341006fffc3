"""Regions say why they are a change, over HTTP (issue 29): a fused map with a chair removed
and a floor patch the scan's path never reached, run by the real service and worker."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from app.db.models import JobStatus
from app.testing.files import ply_bytes
from app.testing.service import ServiceProcess
from tests.helpers.fused_rooms import CHAIR, fused_room


def test_regions_carry_evidence_and_uncovered_places_are_listed_apart(
    service_factory: Callable[..., ServiceProcess],
) -> None:
    rng = np.random.default_rng(5)
    reference = fused_room(rng, box=CHAIR)
    scan = fused_room(rng, floor_hole=([3.6, 1.0], [4.8, 2.0]))
    service = service_factory(workers=1)
    with service.client() as client:
        site = client.post("/api/v1/sites", json={"name": "office"}).json()
        scans_path = f"/api/v1/sites/{site['id']}/scans"
        response = client.post(
            scans_path,
            params={"reference": "true", "filename": "monday.ply"},
            content=ply_bytes(reference),
        )
        assert response.status_code == 201, response.text
        response = client.post(
            scans_path, params={"filename": "tuesday.ply"}, content=ply_bytes(scan)
        )
        assert response.status_code == 202, response.text
        job = service.wait_for_job(client, response.json()["job"]["id"], timeout=180)
        assert job["status"] == JobStatus.SUCCEEDED, job
        assert job["changed"] is True
        regions = client.get(f"/api/v1/jobs/{job['id']}/regions", params={"limit": 1000}).json()
        regions = regions["items"]
        removed = [region for region in regions if region["kind"] == "removed"]
        assert len(removed) == 1 and removed[0]["n_points"] > 300  # the chair
        assert removed[0]["evidence"] in {"seen_empty", "surface_moved"}
        assert 0.0 < removed[0]["confidence"] <= 1.0
        # the floor the chair hid from the reference, seen by the scan: that surface moved
        for region in regions:
            if region["kind"] == "added":
                assert region["evidence"] == "surface_moved" and region["bbox_max"][2] < 0.05
        uncertain = job["uncertain_regions"]
        assert uncertain and {region["evidence"] for region in uncertain} == {"no_coverage"}
        hole = [
            region
            for region in uncertain
            if region["kind"] == "removed" and 3.6 < region["centroid"][0] < 4.8
        ]
        assert hole and hole[0]["bbox_max"][2] < 0.05  # the floor patch, not counted
        assert job["n_regions"] == len(regions)
