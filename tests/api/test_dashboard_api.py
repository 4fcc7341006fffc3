"""What the dashboard needs from the API (issue 19): file names on jobs, paged regions,
site deletion with running jobs, re-runs and the capabilities (upload formats, detectors)."""

from __future__ import annotations

from datetime import timedelta
from typing import Any

import httpx
from sqlalchemy import update

from app.clock import utc_now
from app.core.formats import SUPPORTED_FORMATS
from app.db.models import Job, JobStatus, ReferenceHistory
from app.db.session import transaction
from app.testing.files import ply_bytes
from app.testing.scenes import room_points
from tests.helpers.database import count_rows, counted_selects
from tests.helpers.http import assert_error, create_site, site_with_reference, upload
from tests.helpers.jobs import finish_job, random_regions
from tests.helpers.server import ApiServer


def upload_scan(client: httpx.Client, site_id: str, filename: str, seed: int) -> dict[str, Any]:
    """Upload a scan to compare (PCA); the answer with its scan and job."""
    response = upload(
        client, site_id, ply_bytes(room_points(1500, seed=seed)), filename=filename, method="pca"
    )
    assert response.status_code == 202, response.text
    return response.json()


def test_jobs_name_their_reference_and_scan_files(writer: httpx.Client) -> None:
    site = create_site(writer)
    reference = upload(
        writer,
        site["id"],
        ply_bytes(room_points(2000, seed=1)),
        filename="hall-monday.ply",
        reference=True,
    ).json()["scan"]
    answer = upload_scan(writer, site["id"], "hall-tuesday.ply", seed=2)
    assert answer["job"]["reference_filename"] == reference["filename"] == "hall-monday.ply"
    assert answer["job"]["scan_filename"] == "hall-tuesday.ply"
    job = writer.get(f"/api/v1/jobs/{answer['job']['id']}").json()
    assert (job["reference_filename"], job["scan_filename"]) == (
        "hall-monday.ply",
        "hall-tuesday.ply",
    )
    listed = writer.get(f"/api/v1/sites/{site['id']}/jobs").json()["items"]
    assert [(item["reference_filename"], item["scan_filename"]) for item in listed] == [
        ("hall-monday.ply", "hall-tuesday.ply")
    ]


def test_the_job_list_reads_the_file_names_in_a_fixed_number_of_queries(
    api: ApiServer, writer: httpx.Client
) -> None:
    site, _reference = site_with_reference(writer)
    names = [f"scan-{index}.ply" for index in range(8)]
    for index, name in enumerate(names):
        upload_scan(writer, site["id"], name, seed=10 + index)
    url = f"/api/v1/sites/{site['id']}/jobs"
    writer.get(url, params={"limit": 1})  # warm the session and token caches
    with counted_selects(api.settings) as one_job_queries:
        one = writer.get(url, params={"limit": 1}).json()["items"]
    with counted_selects(api.settings) as eight_job_queries:
        eight = writer.get(url, params={"limit": 8}).json()["items"]
    assert [job["scan_filename"] for job in one] == names[-1:]
    assert sorted(job["scan_filename"] for job in eight) == sorted(names)
    assert len(eight_job_queries) == len(one_job_queries), eight_job_queries


def regions_of(
    client: httpx.Client, job_id: str, **query: Any
) -> tuple[list[dict], str | None, int]:
    """One page of a job's regions, the next cursor and the X-Total-Count."""
    response = client.get(f"/api/v1/jobs/{job_id}/regions", params=query)
    assert response.status_code == 200, response.text
    page = response.json()
    return page["items"], page["next_cursor"], int(response.headers["X-Total-Count"])


def test_regions_are_filtered_sorted_and_paged(api: ApiServer, writer: httpx.Client) -> None:
    site, reference = site_with_reference(writer)
    answer = upload_scan(writer, site["id"], "many-regions.ply", seed=3)
    job_id = answer["job"]["id"]
    regions = random_regions(120, seed=4)
    finish_job(api, job_id, reference["n_points"], answer["scan"]["n_points"], regions=regions)

    everything, next_cursor, total = regions_of(writer, job_id, limit=1000)
    assert total == len(everything) == len(regions) and next_cursor is None
    assert [region["n_points"] for region in everything] == [r.n_points for r in regions]
    first_page, next_cursor, total = regions_of(writer, job_id)  # 50 a page unless asked
    assert len(first_page) == 50 and total == len(regions) and next_cursor

    removed_large = [r for r in regions if r.kind == "removed" and r.n_points >= 1000]
    expected = sorted(removed_large, key=lambda r: -r.max_distance)
    pages: list[dict] = []
    cursor: str | None = None
    for _ in range(len(expected) // 25 + 1):
        query = {"kind": "removed", "min_points": 1000, "sort": "max_distance", "order": "desc"}
        page, cursor, total = regions_of(
            writer, job_id, **query, limit=25, **({"cursor": cursor} if cursor else {})
        )
        assert total == len(expected)
        assert len(page) <= 25
        pages += page
        if cursor is None:
            break
    assert cursor is None
    assert [region["max_distance"] for region in pages] == [r.max_distance for r in expected]
    assert {region["kind"] for region in pages} == {"removed"}

    by_points, _, _ = regions_of(writer, job_id, sort="n_points", limit=5)
    assert [region["n_points"] for region in by_points] == sorted(r.n_points for r in regions)[:5]

    detail = assert_error(
        writer.get(f"/api/v1/jobs/{job_id}/regions", params={"sort": "colour"}), 422, "invalid_sort"
    )
    assert "n_points" in detail
    assert_error(writer.get(f"/api/v1/jobs/{job_id}/regions", params={"limit": 0}), 422)
    assert_error(
        writer.get(f"/api/v1/jobs/{job_id}/regions", params={"cursor": "not-ours"}),
        400,
        "bad_cursor",
    )
    assert_error(writer.get(f"/api/v1/jobs/{job_id}/regions", params={"order": "up"}), 422)
    detail = assert_error(
        writer.get(f"/api/v1/jobs/{job_id}/regions", params={"kind": "gone"}), 422
    )
    assert "removed" in detail
    assert_error(writer.get(f"/api/v1/jobs/{'0' * 32}/regions"), 404)
    stranger = api.client(api.token("writer"))
    assert_error(stranger.get(f"/api/v1/jobs/{job_id}/regions"), 404)


def test_rerun_a_job_with_another_detector(api: ApiServer, writer: httpx.Client) -> None:
    site, _reference = site_with_reference(writer)
    original = upload_scan(writer, site["id"], "rerun-me.ply", seed=5)["job"]
    response = writer.post(
        f"/api/v1/jobs/{original['id']}/rerun",
        json={"method": "gmm", "variant": "paper", "params": {"max_points": 500}},
    )
    assert response.status_code == 202, response.text
    rerun = response.json()
    assert rerun["id"] != original["id"]
    assert (rerun["method"], rerun["variant"], rerun["params"]) == (
        "gmm",
        "paper",
        {"max_points": 500},
    )
    assert rerun["status"] == "queued"
    for field in ("reference_scan_id", "scan_id", "site_id", "scan_filename"):
        assert rerun[field] == original[field]

    same = writer.post(f"/api/v1/jobs/{rerun['id']}/rerun").json()
    assert (same["method"], same["variant"], same["params"]) == (
        "gmm",
        "paper",
        {"max_points": 500},
    )
    other_method = writer.post(f"/api/v1/jobs/{rerun['id']}/rerun", json={"method": "pca"}).json()
    assert (other_method["method"], other_method["variant"], other_method["params"]) == (
        "pca",
        "paper",
        {},
    )
    key = {"Idempotency-Key": "rerun-once"}
    first = writer.post(f"/api/v1/jobs/{original['id']}/rerun", json={"method": "pca"}, headers=key)
    again = writer.post(f"/api/v1/jobs/{original['id']}/rerun", json={"method": "pca"}, headers=key)
    assert first.status_code == again.status_code == 202
    assert first.json()["id"] == again.json()["id"]
    listed = writer.get(f"/api/v1/sites/{site['id']}/jobs").json()["items"]
    assert len(listed) == 5

    detail = assert_error(
        writer.post(f"/api/v1/jobs/{original['id']}/rerun", json={"method": "magic"}),
        422,
        "invalid_detector",
    )
    assert "magic" in detail
    assert_error(
        writer.post(f"/api/v1/jobs/{original['id']}/rerun", json={"params": {"bogus": 1}}),
        422,
        "invalid_detector",
    )
    assert_error(writer.post(f"/api/v1/jobs/{original['id']}/rerun", json={"colour": 1}), 422)
    assert_error(writer.post(f"/api/v1/jobs/{'0' * 32}/rerun"), 404)
    stranger = api.client(api.token("writer", "another-organisation-rerun"))
    assert_error(stranger.post(f"/api/v1/jobs/{original['id']}/rerun"), 404)
    reader = api.client(api.token("reader"))
    assert_error(reader.post(f"/api/v1/jobs/{original['id']}/rerun"), 403)


def test_delete_refuses_while_a_job_runs_and_takes_queued_ones(
    api: ApiServer, writer: httpx.Client
) -> None:
    site, _reference = site_with_reference(writer)
    running = upload_scan(writer, site["id"], "running.ply", seed=6)["job"]
    queued = upload_scan(writer, site["id"], "queued.ply", seed=7)["job"]
    with transaction(api.settings.sqlalchemy_url) as session:
        session.execute(
            update(Job)
            .where(Job.id == running["id"])
            .values(status=JobStatus.RUNNING, lease_expires_at=utc_now() + timedelta(minutes=5))
        )
    detail = assert_error(
        writer.delete(f"/api/v1/sites/{site['id']}"), 409, "site_has_running_jobs"
    )
    assert running["id"] in detail
    assert writer.get(f"/api/v1/sites/{site['id']}").status_code == 200
    assert count_rows(api, Job, site_id=site["id"]) == 2

    # a running job whose worker died (lease expired) does not block the deletion
    with transaction(api.settings.sqlalchemy_url) as session:
        session.execute(
            update(Job)
            .where(Job.id == running["id"])
            .values(lease_expires_at=utc_now() - timedelta(minutes=5))
        )
    assert writer.delete(f"/api/v1/sites/{site['id']}").status_code == 204
    for job in (running, queued):
        assert_error(writer.get(f"/api/v1/jobs/{job['id']}"), 404)
    assert count_rows(api, ReferenceHistory, site_id=site["id"]) == 0
    assert not (api.settings.scans_dir / site["id"]).exists()


def test_site_edit_and_delete_respect_roles_and_organisations(api: ApiServer) -> None:
    organisation = "org-site-roles"
    writer = api.client(api.token("writer", organisation))
    reader = api.client(api.token("reader", organisation))
    stranger = api.client(api.token("writer", "org-site-roles-other"))
    site = create_site(writer)
    url = f"/api/v1/sites/{site['id']}"
    assert_error(reader.patch(url, json={"name": "renamed"}), 403)
    assert_error(reader.delete(url), 403)
    assert_error(stranger.patch(url, json={"name": "renamed"}), 404)
    assert_error(stranger.delete(url), 404)
    assert reader.get(url).json()["name"] == site["name"]
    detail = assert_error(
        writer.patch(url, json={"detector": {"method": "planes", "variant": "nope"}}),
        422,
        "invalid_detector",
    )
    assert "nope" in detail


def test_capabilities_list_what_the_server_reads_and_runs(api: ApiServer) -> None:
    reader = api.client(api.token("reader"))
    capabilities = reader.get("/api/v1/capabilities").json()
    assert capabilities["upload_formats"] == list(SUPPORTED_FORMATS)
    assert capabilities["upload_extensions"] == [f".{name}" for name in SUPPORTED_FORMATS]
    assert {"gmm", "pca", "planes"} <= set(capabilities["detector_methods"])
    assert set(capabilities["detector_variants"]) == {"improved", "paper"}
    assert capabilities["default_detector"]["method"] in capabilities["detector_methods"]
    assert_error(httpx.get(f"{api.base_url}/api/v1/capabilities"), 401)
