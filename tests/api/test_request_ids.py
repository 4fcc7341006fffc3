"""One request id from an upload to the worker that ran its job, in JSON log lines.

An upload with ``X-Request-ID: abc123`` through a real API process stores ``abc123`` on the
job row; a real consumer (with the fast pipeline stand-in) runs the job, and every line it
logs about the job carries ``request_id: abc123`` and the job id.  Every line of both processes
is one JSON object.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

import httpx
import pytest
from pydantic import ValidationError

from app.config import Settings
from app.db.migrate import upgrade_to_head
from app.db.session import transaction
from app.log import bind_request_id, make_handler, remember_job_request_id
from app.services.auth import create_token
from app.testing.files import ply_bytes
from app.testing.scenes import room_points
from app.testing.service import ConsumerProcess, api_process
from tests.helpers.http import create_site, site_with_reference, unique_name, upload
from tests.helpers.jobs import FAST_LEASES, load_job, wait_for_status


def json_lines(log: str) -> list[dict[str, Any]]:
    """Every line of ``log`` parsed as JSON (a line that is not JSON fails the test)."""
    entries = []
    for line in log.splitlines():
        if not line.strip():
            continue
        try:
            entries.append(json.loads(line))
        except json.JSONDecodeError:
            pytest.fail(f"log line is not JSON: {line!r}")
    return entries


def wait_for_lines(
    log_path: Path, wanted: set[str], job_id: str, timeout: float = 20.0
) -> list[dict[str, Any]]:
    """The log's entries about ``job_id`` once their messages include ``wanted``."""
    deadline = time.monotonic() + timeout
    while True:
        entries = [
            entry
            for entry in json_lines(log_path.read_text(errors="replace"))
            if entry.get("job_id") == job_id
        ]
        messages = {str(entry["message"]) for entry in entries}
        if all(any(word in message for message in messages) for word in wanted):
            return entries
        if time.monotonic() > deadline:
            raise AssertionError(f"{wanted} not all logged for job {job_id}: {messages}")
        time.sleep(0.1)


def test_an_uploads_request_id_is_stored_on_its_job_and_in_every_worker_line(
    tmp_path: Path,
) -> None:
    settings = Settings(data_dir=tmp_path / "data", **FAST_LEASES)
    settings.data_dir.mkdir(parents=True)
    upgrade_to_head(settings.sqlalchemy_url)
    with transaction(settings.sqlalchemy_url) as session:
        token = create_token(session, unique_name("org"), "writer")
    api_log = tmp_path / "api.log"
    with api_process(settings, api_log, env={"SCANDIFF_LOG_FORMAT": "json"}) as base_url:
        client = httpx.Client(
            base_url=base_url, headers={"Authorization": f"Bearer {token}"}, timeout=60
        )
        site = create_site(client)
        reference = ply_bytes(room_points(3000, seed=1))
        assert upload(client, site["id"], reference, reference=True).status_code == 201
        response = upload(
            client,
            site["id"],
            ply_bytes(room_points(2500, seed=2)),
            headers={"X-Request-ID": "abc123"},
            method="pca",
        )
        assert response.status_code == 202, response.text
        assert response.headers["x-request-id"] == "abc123"
        job_id = response.json()["job"]["id"]
        assert response.json()["job"]["request_id"] == "abc123"
        assert load_job(settings, job_id).request_id == "abc123"  # on the row itself

        consumer = ConsumerProcess(settings, workers=1, log_path=tmp_path / "consumer.log")
        try:
            job = wait_for_status(settings, job_id, ("succeeded", "failed"), timeout=120)
            assert job.status == "succeeded", (job.error, consumer.log())
            worker_lines = wait_for_lines(
                consumer.log_path, {"job claimed", "job succeeded", "executed in"}, job_id
            )
        finally:
            consumer.stop()
        read = client.get(f"/api/v1/jobs/{job_id}")
        assert read.json()["request_id"] == "abc123"
        client.close()

    # the worker: every line about the job carries the request id, its own lines and Huey's
    assert {entry["request_id"] for entry in worker_lines} == {"abc123"}, worker_lines
    assert {"scandiff.jobs", "huey"} <= {entry["logger"] for entry in worker_lines}
    assert {"claimed", "loading", "comparing", "succeeded"} <= {
        entry.get("stage") for entry in worker_lines
    }
    json_lines(consumer.log())  # every consumer line is JSON

    # the API: every line is JSON; every line of a request carries its id, the upload's enqueue too
    api_entries = json_lines(api_log.read_text())
    requests = [entry for entry in api_entries if entry.get("event") == "request"]
    assert len(requests) >= 5 and all(entry.get("request_id") for entry in requests)
    enqueued = [entry for entry in api_entries if entry.get("job_id") == job_id]
    assert [(entry["message"], entry["request_id"]) for entry in enqueued] == [
        ("job enqueued", "abc123")
    ]
    assert any(entry["logger"].startswith("uvicorn") for entry in api_entries)


@pytest.mark.parametrize(
    "supplied", ["has spaces", "x" * 65, "semi;colon", ""], ids=["space", "long", "symbol", "empty"]
)
def test_a_malformed_request_id_is_replaced_by_a_generated_one_on_the_job_too(
    writer: httpx.Client, supplied: str
) -> None:
    site, _ = site_with_reference(writer)
    response = upload(
        writer, site["id"], ply_bytes(room_points(2000, seed=4)), headers={"X-Request-ID": supplied}
    )
    assert response.status_code == 202, response.text
    generated = response.headers["x-request-id"]
    assert generated != supplied and len(generated) == 32
    assert response.json()["job"]["request_id"] == generated


def test_a_job_created_by_post_jobs_keeps_that_requests_id(writer: httpx.Client) -> None:
    site, reference = site_with_reference(writer)
    first = upload(writer, site["id"], ply_bytes(room_points(2000, seed=5)))
    assert first.status_code == 202, first.text
    response = writer.post(
        "/api/v1/jobs",
        json={"reference_scan_id": reference["id"], "scan_id": first.json()["scan"]["id"]},
        headers={"X-Request-ID": "rerun-7.b_c"},
    )
    assert response.status_code == 202, response.text
    assert response.json()["request_id"] == "rerun-7.b_c"
    job = writer.get(f"/api/v1/jobs/{response.json()['id']}").json()
    assert job["request_id"] == "rerun-7.b_c"
    assert first.json()["job"]["request_id"] == first.headers["x-request-id"]


def test_text_lines_carry_the_request_and_job_ids(capsys: pytest.CaptureFixture[str]) -> None:
    logger = logging.getLogger(f"scandiff.test.{unique_name('text')}")
    logger.propagate = False
    logger.setLevel(logging.INFO)
    logger.addHandler(make_handler("text"))
    with bind_request_id("req-9"):
        logger.info("in a request")
    remember_job_request_id("job-42", "req-10")
    logger.info("about a job", extra={"job_id": "job-42"})
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 2
    assert " INFO " in lines[0] and lines[0].endswith("in a request request_id=req-9")
    assert lines[1].endswith("about a job job_id=job-42 request_id=req-10")


def test_log_format_setting_accepts_json_or_text_only() -> None:
    assert Settings(log_format=" TEXT ").log_format == "text"
    assert Settings().log_format == "json"
    with pytest.raises(ValidationError, match="'json' or 'text'"):
        Settings(log_format="xml")
