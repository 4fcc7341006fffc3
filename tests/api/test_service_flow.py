"""The whole service as users run it: ``scandiff serve`` (uvicorn + real job consumer) in its own
process group, driven over HTTP, then killed in the middle of an upload and started again.

One service lifetime covers it all because starting one costs seconds: create a site, upload a
reference (raw PLY) and scans (multipart LAZ, raw PCD with an Idempotency-Key), wait for the real
worker to finish both jobs, check regions and labels and that the result equals ``compare()`` on
the same files, then SIGKILL the whole process group while a slow upload is streaming, restart,
and check that every site, scan, job and result is unchanged and the half upload left nothing.
"""

from __future__ import annotations

import io
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import httpx
import numpy as np
import pytest

from app.core.datasets.scenes import raycast_scene
from app.core.formats import read_point_cloud
from app.core.jsonable import json_safe
from app.core.pipeline import compare
from app.db.models import JobStatus
from app.testing.files import las_bytes, pcd_bytes, ply_bytes
from app.testing.service import ServiceProcess

ServiceFactory = Callable[..., ServiceProcess]


def wait_succeeded(service: ServiceProcess, client: httpx.Client, job_id: str) -> dict[str, Any]:
    job = service.wait_for_job(client, job_id, timeout=120)
    assert job["status"] == JobStatus.SUCCEEDED, job
    return job


def load_labels(content: bytes) -> dict[str, np.ndarray]:
    with np.load(io.BytesIO(content)) as archive:
        return {name: archive[name] for name in archive.files}


def check_results(client: httpx.Client, job: dict[str, Any], n_reference: int) -> None:
    assert job["progress"] == pytest.approx(1.0)
    assert job["score"] is not None and job["threshold"] is not None
    assert isinstance(job["changed"], bool)
    regions = client.get(f"/api/v1/jobs/{job['id']}/regions", params={"limit": 1000}).json()
    regions = regions["items"]
    assert len(regions) == job["n_regions"]
    assert all(region["kind"] in ("added", "removed") for region in regions)
    labels = load_labels(client.get(f"/api/v1/jobs/{job['id']}/labels").content)
    assert sorted(labels) == sorted(
        ["reference_changed", "scan_changed", "reference_label", "scan_label"]
    )
    assert labels["reference_label"].shape == (n_reference,)
    for file_format in ("ply", "las"):
        response = client.get(f"/api/v1/jobs/{job['id']}/labels", params={"format": file_format})
        assert response.status_code == 200, response.text


def check_same_as_local_compare(
    client: httpx.Client, job: dict[str, Any], reference_id: str
) -> None:
    reference_cloud = read_point_cloud(
        client.get(f"/api/v1/scans/{reference_id}/file").content, filename="r.ply"
    )
    scan = client.get(f"/api/v1/scans/{job['scan_id']}").json()
    scan_cloud = read_point_cloud(
        client.get(f"/api/v1/scans/{job['scan_id']}/file").content, filename=scan["filename"]
    )
    local = compare(
        reference_cloud,
        scan_cloud,
        method=job["method"],
        variant=job["variant"],
        params=job["params"],
    )
    # Same inputs and parameters, same result; the tolerance covers last-bit differences of
    # floating-point reductions between processes (seen: relative 3e-5 after registration).
    assert job["score"] == pytest.approx(local.score, rel=1e-3), (job, local.to_json_dict())
    assert job["changed"] == local.changed
    assert job["effective_params"] == json_safe(local.params)  # what a replay needs
    labels = load_labels(client.get(f"/api/v1/jobs/{job['id']}/labels").content)
    assert np.mean(labels["scan_label"] == local.scan_label) > 0.99
    assert np.mean(labels["reference_label"] == local.reference_label) > 0.99


def kill_during_a_slow_upload(service: ServiceProcess, scans_path: str, head: bytes) -> None:
    """Stream an upload slowly, SIGKILL the service once it reached tmp/, as a power cut."""
    stop_sending = threading.Event()

    def slow_body() -> Iterator[bytes]:
        yield head
        while not stop_sending.is_set():
            yield b"0" * 4096
            time.sleep(0.01)

    def send() -> None:
        with service.client(timeout=30) as sender, pytest.raises(httpx.HTTPError):
            sender.post(scans_path, params={"filename": "cut.ply"}, content=slow_body())

    sender_thread = threading.Thread(target=send, daemon=True)
    sender_thread.start()
    tmp_dir = service.data_dir / "tmp"
    deadline = time.monotonic() + 30
    while not any(tmp_dir.glob("*.part")):
        assert time.monotonic() < deadline, "the upload never reached the temporary directory"
        time.sleep(0.05)
    service.kill()
    stop_sending.set()
    sender_thread.join(timeout=30)
    assert any(tmp_dir.glob("*.part"))  # what the power cut left


def test_the_whole_flow_then_a_kill_mid_upload_and_a_restart(
    service_factory: ServiceFactory,
) -> None:
    service = service_factory(workers=1)
    pair = raycast_scene(n_points=3000, change="box", random_state=1)
    with service.client() as client:
        response = client.post(
            "/api/v1/sites",
            json={"name": "lab", "detector": {"method": "pca", "variant": "improved"}},
        )
        assert response.status_code == 201, response.text
        site = response.json()
        scans_path = f"/api/v1/sites/{site['id']}/scans"
        response = client.post(
            scans_path,
            params={"reference": "true", "filename": "reference.ply"},
            content=ply_bytes(pair.reference),
            headers={"Content-Type": "application/octet-stream"},
        )
        assert response.status_code == 201, response.text
        reference = response.json()["scan"]
        response = client.post(
            scans_path,
            files={
                "file": (
                    "monday.laz",
                    las_bytes(pair.scan, compress=True),
                    "application/octet-stream",
                )
            },
        )
        assert response.status_code == 202, response.text
        laz_job = response.json()["job"]
        pcd_upload: dict[str, Any] = {
            "params": {"filename": "tuesday.pcd", "method": "planes"},
            "content": pcd_bytes(pair.scan),
            "headers": {"Content-Type": "application/octet-stream", "Idempotency-Key": "tue-1"},
        }
        response = client.post(scans_path, **pcd_upload)
        assert response.status_code == 202, response.text
        pcd_job = response.json()["job"]
        assert pcd_job["method"] == "planes"

        jobs = [wait_succeeded(service, client, job["id"]) for job in (laz_job, pcd_job)]
        for job in jobs:
            assert job["reference_scan_id"] == reference["id"]
            check_results(client, job, reference["n_points"])
        check_same_as_local_compare(client, jobs[0], reference["id"])
        timeline = client.get(f"/api/v1/sites/{site['id']}/jobs").json()
        assert [item["id"] for item in timeline["items"]] == [pcd_job["id"], laz_job["id"]]

        scan_ids = [item["id"] for item in client.get(scans_path).json()["items"]]
        paths = [
            "/api/v1/sites",
            f"/api/v1/sites/{site['id']}",
            scans_path,
            f"/api/v1/sites/{site['id']}/jobs",
            *(f"/api/v1/scans/{scan_id}" for scan_id in scan_ids),
            *(f"/api/v1/jobs/{job['id']}" for job in jobs),
            *(f"/api/v1/jobs/{job['id']}/regions" for job in jobs),
        ]
        before = {path: client.get(path).json() for path in paths}
        file_paths = [
            *(f"/api/v1/scans/{scan_id}/file" for scan_id in scan_ids),
            *(f"/api/v1/jobs/{job['id']}/labels" for job in jobs),
        ]
        files_before = {path: client.get(path).content for path in file_paths}

    kill_during_a_slow_upload(service, scans_path, ply_bytes(pair.scan)[:1000])
    service.start()

    assert list((service.data_dir / "tmp").iterdir()) == []
    stored = sorted(path.name for path in (service.data_dir / "scans" / site["id"]).iterdir())
    scans = [before[f"/api/v1/scans/{scan_id}"] for scan_id in scan_ids]
    expected = {f"{scan['id']}.{scan['format']}" for scan in scans}
    # the reference's k-NN geometry cache stays beside it (app/jobs/geometry.py)
    reference_cache = f"{reference['id']}.geometry"
    assert reference_cache in stored
    assert stored == sorted(expected | {reference_cache})
    with service.client() as client:
        assert {path: client.get(path).json() for path in paths} == before
        assert {path: client.get(path).content for path in file_paths} == files_before
        retried = client.post(scans_path, **pcd_upload)
        assert retried.status_code == 202
        assert retried.json()["job"]["id"] == pcd_job["id"]
        assert len(client.get(scans_path).json()["items"]) == len(scan_ids)
