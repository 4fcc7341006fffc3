"""Jobs: creation and validation, idempotent retries (uploads and jobs), the site timeline with
filters and paging, regions, and labels as npz/ply/las."""

from __future__ import annotations

import io
import time
from concurrent.futures import ThreadPoolExecutor

import httpx
import laspy
import numpy as np
import pytest
from plyfile import PlyData

from app.clock import utc_now
from app.db.models import IdempotencyRecord, Job, JobStatus, Scan
from app.testing.files import las_bytes, pcd_bytes, ply_bytes
from app.testing.scenes import room_points as make_points
from tests.helpers.database import count_rows as count
from tests.helpers.http import assert_error, site_with_reference, unique_name, upload
from tests.helpers.jobs import finish_job
from tests.helpers.server import ApiServer


@pytest.fixture
def site_scans(writer: httpx.Client) -> tuple[dict, dict, dict]:
    """A site, its reference and one more scan (whose upload job is left queued)."""
    site, reference = site_with_reference(writer)
    response = upload(writer, site["id"], ply_bytes(make_points(2000, seed=3)))
    assert response.status_code == 202, response.text
    return site, reference, response.json()["scan"]


def test_post_jobs_queues_any_comparison(
    writer: httpx.Client, site_scans: tuple[dict, dict, dict]
) -> None:
    site, reference, scan = site_scans
    response = writer.post(
        "/api/v1/jobs",
        json={
            "reference_scan_id": scan["id"],
            "scan_id": reference["id"],
            "method": "pca",
            "variant": "paper",
            "params": {"random_state": 3},
        },
    )
    assert response.status_code == 202, response.text
    job = response.json()
    assert (job["reference_scan_id"], job["scan_id"]) == (scan["id"], reference["id"])
    assert (job["method"], job["variant"], job["params"]) == ("pca", "paper", {"random_state": 3})
    assert job["status"] == JobStatus.QUEUED and job["progress"] == 0.0 and job["attempts"] == 0
    expected_keys = {
        "id", "site_id", "reference_scan_id", "scan_id", "status", "progress", "attempts",
        "method", "variant", "params", "score", "threshold", "changed", "registration",
        "n_regions", "error", "timings", "created_at", "started_at", "finished_at",
    }  # fmt: skip
    assert expected_keys <= set(job)
    fetched = writer.get(f"/api/v1/jobs/{job['id']}").json()
    assert fetched["id"] == job["id"] and fetched["site_id"] == site["id"]
    # Defaults come from the site's detector.
    response = writer.post(
        "/api/v1/jobs", json={"reference_scan_id": reference["id"], "scan_id": scan["id"]}
    )
    assert (response.json()["method"], response.json()["variant"]) == ("gmm", "improved")


def test_post_jobs_validation(writer: httpx.Client, site_scans: tuple[dict, dict, dict]) -> None:
    _site, reference, scan = site_scans
    _other_site, other_reference = site_with_reference(writer)
    pair = {"reference_scan_id": reference["id"], "scan_id": scan["id"]}
    assert_error(
        writer.post("/api/v1/jobs", json={**pair, "scan_id": other_reference["id"]}),
        422,
        "scans_of_different_sites",
    )
    assert_error(writer.post("/api/v1/jobs", json={**pair, "scan_id": "0" * 32}), 404)
    detail = assert_error(
        writer.post("/api/v1/jobs", json={**pair, "params": {"no_such_knob": 1}}),
        422,
        "invalid_detector",
    )
    assert "no_such_knob" in detail
    detail = assert_error(
        writer.post("/api/v1/jobs", json={**pair, "params": {"recover_stations": "maybe"}}),
        422,
        "invalid_detector",
    )
    assert "recover_stations" in detail and '"auto"' in detail
    assert_error(writer.post("/api/v1/jobs", json={**pair, "method": "bogus"}), 422)
    assert_error(writer.post("/api/v1/jobs", json={"scan_id": scan["id"]}), 422)
    assert_error(writer.post("/api/v1/jobs", json={**pair, "params": [1, 2]}), 422)
    assert_error(
        writer.post("/api/v1/jobs", json={**pair, "params": {"registration": 5}}),
        422,
        "invalid_detector",
    )


def test_a_retried_job_creation_returns_the_first_response(
    api: ApiServer, writer: httpx.Client, site_scans: tuple[dict, dict, dict]
) -> None:
    site, reference, scan = site_scans
    body = {"reference_scan_id": reference["id"], "scan_id": scan["id"], "method": "pca"}
    headers = {"Idempotency-Key": "job-retry-1"}
    first = writer.post("/api/v1/jobs", json=body, headers=headers)
    second = writer.post("/api/v1/jobs", json=body, headers=headers)
    assert first.status_code == second.status_code == 202
    assert first.json() == second.json()
    assert count(api, Job, site_id=site["id"]) == 2  # the upload's job and this one
    detail = assert_error(
        writer.post("/api/v1/jobs", json={**body, "method": "gmm"}, headers=headers),
        422,
        "idempotency_key_reused",
    )
    assert "different request" in detail
    assert count(api, Job, site_id=site["id"]) == 2
    # Keys are per organisation: another organisation may use the same key.
    stranger = api.client(api.token("writer"))
    assert_error(stranger.post("/api/v1/jobs", json=body, headers=headers), 404)
    assert_error(writer.post("/api/v1/jobs", json=body, headers={"Idempotency-Key": ""}), 422)


@pytest.mark.parametrize("multipart", [False, True], ids=["raw", "multipart"])
def test_a_retried_upload_returns_the_first_response(
    api: ApiServer, writer: httpx.Client, multipart: bool
) -> None:
    site, _reference = site_with_reference(writer)
    content = las_bytes(make_points(2000, seed=8), compress=True)
    headers = {"Idempotency-Key": f"upload-{multipart}"}
    first = upload(writer, site["id"], content, filename="a.laz", multipart=multipart,
                   headers=headers)  # fmt: skip
    second = upload(writer, site["id"], content, filename="a.laz", multipart=multipart,
                    headers=headers)  # fmt: skip
    assert first.status_code == second.status_code == 202, first.text
    assert first.json() == second.json()
    assert count(api, Scan, site_id=site["id"]) == 2
    assert count(api, Job, site_id=site["id"]) == 1
    assert len(list((api.settings.scans_dir / site["id"]).iterdir())) == 2
    different = upload(writer, site["id"], pcd_bytes(make_points(900)), filename="b.pcd",
                       multipart=multipart, headers=headers)  # fmt: skip
    assert_error(different, 422, "idempotency_key_reused")
    assert count(api, Scan, site_id=site["id"]) == 2
    assert len(list((api.settings.scans_dir / site["id"]).iterdir())) == 2
    assert list(api.settings.tmp_dir.iterdir()) == []


def test_a_retried_reference_upload_replays_201(api: ApiServer, writer: httpx.Client) -> None:
    site, _ = site_with_reference(writer)
    content = ply_bytes(make_points(1000, seed=5))
    key = unique_name("reference-once")
    headers = {"Idempotency-Key": key}
    first = upload(writer, site["id"], content, reference=True, headers=headers)
    second = upload(writer, site["id"], content, reference=True, headers=headers)
    assert first.status_code == second.status_code == 201
    assert first.json() == second.json()
    assert count(api, Scan, site_id=site["id"]) == 2
    assert count(api, IdempotencyRecord, key=key) == 1


def test_failed_requests_do_not_consume_the_key(writer: httpx.Client) -> None:
    site, _ = site_with_reference(writer)
    headers = {"Idempotency-Key": "after-a-failure"}
    assert_error(upload(writer, site["id"], b"garbage", filename="x.ply", headers=headers), 400)
    response = upload(writer, site["id"], ply_bytes(make_points(700)), headers=headers)
    assert response.status_code == 202, response.text


def test_the_timeline_filters_and_pages_newest_first(api: ApiServer, writer: httpx.Client) -> None:
    site, reference = site_with_reference(writer)
    jobs = []
    for index in range(5):
        response = upload(writer, site["id"], ply_bytes(make_points(600, seed=20 + index)))
        assert response.status_code == 202, response.text
        jobs.append(response.json()["job"])
        if index == 1:
            time.sleep(0.01)
            middle = utc_now()
    finish_job(api, jobs[0]["id"], reference["n_points"], 600, changed=True)
    finish_job(api, jobs[3]["id"], reference["n_points"], 600, changed=False)
    timeline = f"/api/v1/sites/{site['id']}/jobs"

    def ids(**params: object) -> list[str]:
        response = writer.get(timeline, params=params)
        assert response.status_code == 200, response.text
        return [job["id"] for job in response.json()["items"]]

    newest_first = [job["id"] for job in reversed(jobs)]
    assert ids() == newest_first
    assert ids(status=JobStatus.SUCCEEDED) == [jobs[3]["id"], jobs[0]["id"]]
    assert ids(status=JobStatus.QUEUED) == [jobs[4]["id"], jobs[2]["id"], jobs[1]["id"]]
    assert ids(changed="true") == [jobs[0]["id"]]
    assert ids(changed="false") == [jobs[3]["id"]]
    assert ids(since=middle.isoformat()) == newest_first[:3]
    paged: list[str] = []
    cursor = None
    while True:
        params = {"limit": 2, **({"cursor": cursor} if cursor else {})}
        page = writer.get(timeline, params=params).json()
        paged += [job["id"] for job in page["items"]]
        cursor = page["next_cursor"]
        if not cursor:
            break
    assert paged == newest_first
    assert_error(writer.get(timeline, params={"status": "exploded"}), 422)
    assert_error(writer.get(timeline, params={"since": "yesterday"}), 422)
    assert_error(writer.get(timeline, params={"cursor": "%%%"}), 400)


def test_regions_and_labels_of_a_succeeded_job(
    api: ApiServer, writer: httpx.Client, site_scans: tuple[dict, dict, dict]
) -> None:
    site, reference, scan = site_scans
    job = writer.get(f"/api/v1/sites/{site['id']}/jobs").json()["items"][0]
    assert writer.get(f"/api/v1/jobs/{job['id']}/regions").json() == {
        "items": [],
        "next_cursor": None,
    }
    for file_format in ("npz", "ply", "las"):
        response = writer.get(f"/api/v1/jobs/{job['id']}/labels", params={"format": file_format})
        assert_error(response, 409, "job_not_succeeded")
    shift = np.eye(4)
    shift[:3, 3] = [10.0, 0.0, 0.0]
    scan_region = np.where(np.arange(scan["n_points"]) % 3 == 0, 0, -1).astype(np.int32)
    arrays = finish_job(
        api,
        job["id"],
        reference["n_points"],
        scan["n_points"],
        transform=shift.tolist(),
        scan_region=scan_region,
    )
    regions_per_point = np.concatenate([np.full(reference["n_points"], -1), scan_region])
    fetched = writer.get(f"/api/v1/jobs/{job['id']}").json()
    assert fetched["status"] == JobStatus.SUCCEEDED and fetched["changed"] is True
    regions = writer.get(f"/api/v1/jobs/{job['id']}/regions").json()["items"]
    assert len(regions) == 1
    assert set(regions[0]) == {
        "id", "ordinal", "kind", "n_points", "centroid", "bbox_min", "bbox_max", "mean_distance",
        "max_distance", "evidence", "confidence",
    }  # fmt: skip
    assert regions[0]["kind"] == "added" and regions[0]["ordinal"] == 0

    response = writer.get(f"/api/v1/jobs/{job['id']}/labels")
    assert response.status_code == 200
    with np.load(io.BytesIO(response.content)) as labels:
        assert sorted(labels.files) == sorted(
            ["reference_changed", "scan_changed", "reference_label", "scan_label"]
        )
        np.testing.assert_array_equal(labels["scan_label"], arrays["scan_label"])
    n_total = reference["n_points"] + scan["n_points"]

    response = writer.get(f"/api/v1/jobs/{job['id']}/labels", params={"format": "ply"})
    assert response.status_code == 200, response.text
    vertex = PlyData.read(io.BytesIO(response.content))["vertex"].data
    assert len(vertex) == n_total
    cloud = np.asarray(vertex["cloud"])
    assert (cloud == 0).sum() == reference["n_points"] and (cloud == 1).sum() == scan["n_points"]
    np.testing.assert_array_equal(
        np.asarray(vertex["label"]),
        np.concatenate([arrays["reference_label"], arrays["scan_label"]]),
    )
    np.testing.assert_allclose(
        np.asarray(vertex["distance"]),
        np.concatenate([arrays["reference_distance"], arrays["scan_distance"]]),
    )
    np.testing.assert_array_equal(np.asarray(vertex["region"]), regions_per_point)
    scan_x = np.asarray(vertex["x"])[cloud == 1]
    assert scan_x.min() == pytest.approx(scan["bbox_min"][0] + 10.0, abs=1e-3)  # registered

    response = writer.get(f"/api/v1/jobs/{job['id']}/labels", params={"format": "las"})
    assert response.status_code == 200, response.text
    las = laspy.read(io.BytesIO(response.content))
    assert len(las.points) == n_total
    np.testing.assert_array_equal(
        np.asarray(las["label"]), np.concatenate([arrays["reference_label"], arrays["scan_label"]])
    )
    np.testing.assert_array_equal(np.asarray(las["region"]), regions_per_point)
    assert_error(writer.get(f"/api/v1/jobs/{job['id']}/labels", params={"format": "xyz"}), 422)


def test_concurrent_retries_with_one_key_create_one_scan(
    api: ApiServer, writer: httpx.Client
) -> None:
    site, _reference = site_with_reference(writer)
    content = ply_bytes(make_points(3000, seed=12))
    token = writer.headers["Authorization"]

    def send(_: int) -> httpx.Response:
        with httpx.Client(base_url=api.base_url, headers={"Authorization": token}) as client:
            return upload(client, site["id"], content, headers={"Idempotency-Key": "race"})

    with ThreadPoolExecutor(max_workers=4) as pool:
        responses = list(pool.map(send, range(4)))
    assert {response.status_code for response in responses} == {202}
    assert len({response.text for response in responses}) == 1
    assert count(api, Scan, site_id=site["id"]) == 2
    assert count(api, Job, site_id=site["id"]) == 1
    assert len(list((api.settings.scans_dir / site["id"]).iterdir())) == 2


def test_a_long_poll_answers_once_the_job_ends(
    api: ApiServer, writer: httpx.Client, site_scans: tuple[dict, dict, dict]
) -> None:
    site, reference, scan = site_scans
    job = writer.get(f"/api/v1/sites/{site['id']}/jobs").json()["items"][0]
    assert job["status"] == JobStatus.QUEUED
    with ThreadPoolExecutor(1) as pool:
        waiting = pool.submit(writer.get, f"/api/v1/jobs/{job['id']}", params={"wait": 10})
        time.sleep(0.3)  # the request is waiting (a late start only reads the ended job)
        assert not waiting.done()
        finish_job(api, job["id"], reference["n_points"], scan["n_points"])
        response = waiting.result(timeout=30)
    assert response.status_code == 200, response.text
    assert response.json()["status"] == JobStatus.SUCCEEDED
    assert response.json()["n_regions"] == 1
    # an ended job answers at once, as without ``wait``
    again = writer.get(f"/api/v1/jobs/{job['id']}", params={"wait": 10})
    assert again.json() == writer.get(f"/api/v1/jobs/{job['id']}").json()


def test_a_long_poll_that_runs_out_returns_the_job_as_it_is(
    api: ApiServer, writer: httpx.Client, site_scans: tuple[dict, dict, dict]
) -> None:
    site, _, _ = site_scans
    job = writer.get(f"/api/v1/sites/{site['id']}/jobs").json()["items"][0]
    response = writer.get(f"/api/v1/jobs/{job['id']}", params={"wait": 0.2})
    assert response.status_code == 200 and response.json()["status"] == JobStatus.QUEUED
    assert_error(writer.get(f"/api/v1/jobs/{job['id']}", params={"wait": 11}), 422)
    assert_error(writer.get(f"/api/v1/jobs/{job['id']}", params={"wait": -1}), 422)
    other = api.client(api.token("writer"))  # another organisation: 404, no wait
    assert_error(other.get(f"/api/v1/jobs/{job['id']}", params={"wait": 5}), 404)
