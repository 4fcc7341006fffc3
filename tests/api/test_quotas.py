"""Issue 5 (5): per-organisation caps on unfinished jobs (429) and stored bytes (507), over HTTP.

A server with small caps (3 unfinished jobs, 250,000 stored bytes) and no job consumer, so jobs
stay queued.  Every refusal must leave no scan row, no job row and no file; other organisations
are not affected; ``GET /api/v1/organisation`` reports the numbers.
"""

from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import httpx
import pytest
from sqlalchemy import select, update

from app.db.models import Job, JobStatus, Scan
from app.db.session import transaction
from app.services.quotas import RETRY_AFTER_SECONDS
from app.testing.files import chunked, ply_bytes, ply_of_size
from app.testing.scenes import room_points as make_points
from tests.helpers.database import count_rows
from tests.helpers.http import assert_error, create_site, unique_name, upload
from tests.helpers.server import MAX_UPLOAD_BYTES, ApiServer, fresh_api, running_api

MAX_QUEUED_JOBS = 3
MAX_STORED_BYTES = 250_000


@pytest.fixture(scope="module")
def quota_api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ApiServer]:
    """The app with small quotas on a fresh data directory (no consumer: jobs stay queued)."""
    yield from fresh_api(
        tmp_path_factory,
        "quota-data",
        max_upload_bytes=MAX_UPLOAD_BYTES,
        max_queued_jobs_per_organisation=MAX_QUEUED_JOBS,
        max_stored_bytes_per_organisation=MAX_STORED_BYTES,
    )


def organisation(client: httpx.Client) -> dict[str, Any]:
    response = client.get("/api/v1/organisation")
    assert response.status_code == 200, response.text
    return response.json()


def rows_of(api: ApiServer, organisation_id: str) -> tuple[int, int]:
    """``(scans, jobs)`` rows of the organisation."""
    return (
        count_rows(api, Scan, organisation_id=organisation_id),
        count_rows(api, Job, organisation_id=organisation_id),
    )


def finish_queued_jobs(api: ApiServer, organisation_id: str, n_jobs: int) -> None:
    """Play the worker: mark ``n_jobs`` queued jobs of the organisation as failed (finished)."""
    with transaction(api.settings.sqlalchemy_url) as session:
        job_ids = session.scalars(
            select(Job.id)
            .where(Job.organisation_id == organisation_id, Job.status == JobStatus.QUEUED)
            .limit(n_jobs)
        ).all()
        session.execute(update(Job).where(Job.id.in_(job_ids)).values(status=JobStatus.FAILED))


def test_the_cap_on_unfinished_jobs_answers_429_and_stores_nothing(quota_api: ApiServer) -> None:
    client = quota_api.client(quota_api.token("writer"))
    site = create_site(client)
    reference = upload(client, site["id"], ply_bytes(make_points(1000, seed=1)), reference=True)
    assert reference.status_code == 201, reference.text  # a reference makes no job
    reference_id = reference.json()["scan"]["id"]
    scan_ids = []
    for seed in range(MAX_QUEUED_JOBS):
        response = upload(client, site["id"], ply_bytes(make_points(1000, seed=10 + seed)))
        assert response.status_code == 202, response.text
        scan_ids.append(response.json()["scan"]["id"])
    usage = organisation(client)
    assert usage["queued_jobs"] == MAX_QUEUED_JOBS
    assert usage["max_queued_jobs"] == MAX_QUEUED_JOBS
    rows_before = rows_of(quota_api, usage["id"])
    files_before = quota_api.stored_files()

    refused = {
        "upload": upload(client, site["id"], ply_bytes(make_points(1000, seed=20))),
        "multipart upload": upload(
            client, site["id"], ply_bytes(make_points(1000, seed=20)), multipart=True
        ),
        # Refused before the body is parsed: a robot at the cap does not send a scan in vain.
        "upload of a body never parsed": upload(client, site["id"], b"ply\nnot a point cloud\n"),
        "POST /jobs": client.post(
            "/api/v1/jobs", json={"reference_scan_id": reference_id, "scan_id": scan_ids[0]}
        ),
    }
    for name, response in refused.items():
        detail = assert_error(response, 429, "too_many_queued_jobs")
        assert response.headers["Retry-After"] == str(RETRY_AFTER_SECONDS), name
        assert f"{MAX_QUEUED_JOBS} unfinished jobs" in detail, detail
        assert f"the cap is {MAX_QUEUED_JOBS}" in detail, detail
        assert "SCANDIFF_MAX_QUEUED_JOBS_PER_ORGANISATION" in detail, detail
        assert f"retry after {RETRY_AFTER_SECONDS} s" in detail, detail
    assert rows_of(quota_api, usage["id"]) == rows_before
    assert quota_api.stored_files() == files_before

    # A reference upload makes no job: still accepted at the cap.
    another_reference = upload(
        client, site["id"], ply_bytes(make_points(1000, seed=30)), reference=True
    )
    assert another_reference.status_code == 201, another_reference.text

    # Another organisation is not affected.
    other = quota_api.client(quota_api.token("writer"))
    other_site = create_site(other)
    assert upload(other, other_site["id"], ply_bytes(make_points(1000)), reference=True).is_success
    assert upload(other, other_site["id"], ply_bytes(make_points(1000, seed=2))).status_code == 202
    assert organisation(other)["queued_jobs"] == 1

    # A finished job makes room for one more.
    finish_queued_jobs(quota_api, usage["id"], 1)
    assert organisation(client)["queued_jobs"] == MAX_QUEUED_JOBS - 1
    again = client.post(
        "/api/v1/jobs", json={"reference_scan_id": reference_id, "scan_id": scan_ids[0]}
    )
    assert again.status_code == 202, again.text
    assert_error(upload(client, site["id"], ply_bytes(make_points(1000, seed=21))), 429)


def test_the_storage_cap_answers_507_before_storing_anything(quota_api: ApiServer) -> None:
    client = quota_api.client(quota_api.token("writer"))
    site = create_site(client)
    reference = upload(client, site["id"], ply_of_size(100_000), reference=True)
    assert reference.status_code == 201, reference.text
    usage = organisation(client)
    assert usage["stored_bytes"] == 100_000
    assert usage["max_stored_bytes"] == MAX_STORED_BYTES
    rows_before = rows_of(quota_api, usage["id"])
    files_before = quota_api.stored_files()

    left = MAX_STORED_BYTES - 100_000
    over = ply_of_size(left + 1, seed=4)
    path = f"/api/v1/sites/{site['id']}/scans"
    refused = {
        "raw, Content-Length": upload(client, site["id"], over),
        "raw, chunked": client.post(path, params={"filename": "o.ply"}, content=chunked(over)),
        "multipart": upload(client, site["id"], over, multipart=True),
        "reference": upload(client, site["id"], over, reference=True),
    }
    for name, response in refused.items():
        detail = assert_error(response, 507, "storage_quota_exceeded")
        assert "stores 100000 bytes" in detail, (name, detail)
        assert f"the cap is {MAX_STORED_BYTES}" in detail, (name, detail)
        assert f"{left} bytes left" in detail, (name, detail)
        assert "DELETE /api/v1/sites/" in detail, (name, detail)
    assert str(left + 1) in refused["raw, Content-Length"].json()["detail"]
    assert rows_of(quota_api, usage["id"]) == rows_before
    assert quota_api.stored_files() == files_before

    # Exactly what is left fits; then nothing more does.
    fits = upload(client, site["id"], ply_of_size(left, seed=5))
    assert fits.status_code == 202, fits.text
    assert organisation(client)["stored_bytes"] == MAX_STORED_BYTES
    detail = assert_error(
        upload(client, site["id"], ply_bytes(make_points(300))), 507, "storage_quota_exceeded"
    )
    assert "0 bytes left" in detail

    # Another organisation is not affected.
    other = quota_api.client(quota_api.token("writer"))
    other_site = create_site(other)
    assert upload(other, other_site["id"], ply_of_size(left), reference=True).status_code == 201

    # Deleting a site frees its bytes.
    assert client.delete(f"/api/v1/sites/{site['id']}").status_code == 204
    assert organisation(client)["stored_bytes"] == 0
    new_site = create_site(client)
    assert upload(client, new_site["id"], ply_of_size(left), reference=True).status_code == 201
    assert organisation(client)["stored_bytes"] == left


def test_a_retry_of_an_accepted_upload_replays_even_at_the_cap(quota_api: ApiServer) -> None:
    client = quota_api.client(quota_api.token("writer"))
    site = create_site(client)
    content = ply_of_size(MAX_STORED_BYTES, seed=6)
    key = {"Idempotency-Key": unique_name("quota")}
    first = upload(client, site["id"], content, reference=True, headers=key)
    assert first.status_code == 201, first.text
    retry = upload(client, site["id"], content, reference=True, headers=key)
    assert (retry.status_code, retry.json()) == (201, first.json())
    assert organisation(client)["stored_bytes"] == MAX_STORED_BYTES


def test_concurrent_uploads_never_pass_the_storage_cap(quota_api: ApiServer) -> None:
    token = quota_api.token("writer")
    client = quota_api.client(token)
    site = create_site(client)
    reference = upload(client, site["id"], ply_of_size(100_000), reference=True)
    assert reference.status_code == 201, reference.text
    organisation_id = organisation(client)["id"]
    files_before = len(quota_api.stored_files())
    size = 40_000  # 150,000 left: 3 of these fit, the other 5 must be refused
    contents = [ply_of_size(size, seed=40 + index) for index in range(8)]

    def send(content: bytes) -> int:
        with httpx.Client(
            base_url=quota_api.base_url,
            headers={"Authorization": f"Bearer {token}"},
            timeout=60.0,
        ) as own:
            return upload(own, site["id"], content, reference=True).status_code

    with ThreadPoolExecutor(len(contents)) as pool:
        statuses = sorted(pool.map(send, contents))
    assert statuses == [201] * 3 + [507] * 5, statuses
    usage = organisation(client)
    assert usage["stored_bytes"] == 100_000 + 3 * size <= MAX_STORED_BYTES
    assert rows_of(quota_api, organisation_id) == (4, 0)
    assert len(quota_api.stored_files()) == files_before + 3


def test_concurrent_job_creations_never_pass_the_cap(quota_api: ApiServer) -> None:
    token = quota_api.token("writer")
    client = quota_api.client(token)
    site = create_site(client)
    content = ply_bytes(make_points(1000))
    reference = upload(client, site["id"], content, reference=True).json()["scan"]["id"]
    payload = {"reference_scan_id": reference, "scan_id": reference}

    def send(_: int) -> int:
        with httpx.Client(
            base_url=quota_api.base_url,
            headers={"Authorization": f"Bearer {token}"},
            timeout=60.0,
        ) as own:
            return own.post("/api/v1/jobs", json=payload).status_code

    with ThreadPoolExecutor(8) as pool:
        statuses = sorted(pool.map(send, range(8)))
    assert statuses == [202] * MAX_QUEUED_JOBS + [429] * (8 - MAX_QUEUED_JOBS), statuses
    assert organisation(client)["queued_jobs"] == MAX_QUEUED_JOBS


def test_the_usage_endpoint_reports_the_organisation_to_readers(quota_api: ApiServer) -> None:
    organisation_name = unique_name("org-usage")
    writer = quota_api.client(quota_api.token("writer", organisation_name))
    reader = quota_api.client(quota_api.token("reader", organisation_name))
    site = create_site(writer)
    content = ply_bytes(make_points(1000))
    assert upload(writer, site["id"], content, reference=True).status_code == 201
    assert upload(writer, site["id"], content).status_code == 202
    usage = organisation(reader)
    assert usage == {
        "id": usage["id"],
        "name": organisation_name,
        "queued_jobs": 1,
        "max_queued_jobs": MAX_QUEUED_JOBS,
        "stored_bytes": 2 * len(content),
        "max_stored_bytes": MAX_STORED_BYTES,
    }
    assert_error(quota_api.client().get("/api/v1/organisation"), 401)


def test_unlimited_caps_are_reported_as_null(tmp_path_factory: pytest.TempPathFactory) -> None:
    from app.config import Settings

    settings = Settings(
        data_dir=tmp_path_factory.mktemp("unlimited-data"),
        max_queued_jobs_per_organisation="none",
        max_stored_bytes_per_organisation="unlimited",
    )
    with running_api(settings) as api:
        usage = organisation(api.client(api.token("reader")))
    assert usage["max_queued_jobs"] is None and usage["max_stored_bytes"] is None
    assert usage["queued_jobs"] == 0 and usage["stored_bytes"] == 0
