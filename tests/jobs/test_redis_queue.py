"""The job flow with Redis as the queue (``SCANDIFF_QUEUE_URL=redis://``), on a private server.

Real HTTP against the real app, ``scandiff worker`` processes, and a redis-server of the test's
own on a free port (never the shared one), stopped and started again to play an outage.
"""

from __future__ import annotations

import json
import logging
import os
import signal
from collections.abc import Callable

import httpx
import pytest

from app.config import Settings
from app.jobs.leases import lease_owner_pid
from app.jobs.queue import QUEUE_NAME, enqueue_job, get_huey, queue_backend, queue_health
from app.jobs.recovery import recovery_sweep
from app.testing.files import ply_bytes
from app.testing.redis import RedisServer
from app.testing.scenes import room_points
from app.testing.waiting import wait_until
from tests.helpers.http import site_with_reference, upload, upload_accepted
from tests.helpers.jobs import create_job, load_job, wait_for_status
from tests.helpers.server import running_api
from tests.helpers.worker import WorkerProcess


def hooks_env(**hooks: object) -> dict[str, str]:
    """Environment enabling the job test hooks ``hooks``."""
    return {"SCANDIFF_TESTING": "1", "SCANDIFF_TEST_JOB_HOOKS": json.dumps(hooks)}


def scan_bytes(seed: int) -> bytes:
    """A 3k-point room scan as PLY."""
    return ply_bytes(room_points(3000, seed=seed))


def wait_for_job(client: httpx.Client, job_id: str, timeout: float = 60.0) -> dict[str, object]:
    """Poll the job over HTTP until it succeeded or failed; the job."""
    return wait_until(
        lambda: (
            (job := client.get(f"/api/v1/jobs/{job_id}").json())["status"]
            in ("succeeded", "failed")
            and job
        ),
        timeout,
        f"job {job_id} finished",
        interval=0.1,
    )


def test_upload_runs_on_a_worker_through_redis(
    redis_settings: Settings, worker_factory: Callable[..., WorkerProcess]
) -> None:
    assert queue_backend(redis_settings) == "redis"
    with running_api(redis_settings) as api:
        client = api.client(api.token())
        site, _reference = site_with_reference(client)
        job_id = upload_accepted(client, site["id"], "scan.ply", scan_bytes(2))["job"]["id"]

        # The message waits in Redis (no SQLite queue file is made) until a worker starts.
        assert get_huey(redis_settings).pending_count() == 1
        assert not redis_settings.queue_path.exists()
        worker = worker_factory(redis_settings, concurrency=2)
        job = wait_for_job(client, job_id)

        assert job["status"] == "succeeded", worker.log()
        assert get_huey(redis_settings).pending_count() == 0
        health = wait_until(
            lambda: (
                (h := queue_health(redis_settings)).get("consumer_last_seen_seconds") is not None
                and h
            ),
            20,
            "the worker noted it is alive in Redis",
        )
        assert (health["backend"], health["status"], health["consumer_workers"]) == (
            "redis",
            "ok",
            2,
        )


def test_a_killed_worker_s_job_is_finished_by_another_attempt(
    redis_settings: Settings, worker_factory: Callable[..., WorkerProcess]
) -> None:
    worker = worker_factory(
        redis_settings, concurrency=2, env=hooks_env(sleep_seconds=60, on_attempts=[1])
    )
    worker.wait_for_workers()
    job_id = create_job(redis_settings)
    assert enqueue_job(job_id, redis_settings)
    running = wait_for_status(redis_settings, job_id, ("running",))
    owner_pid = lease_owner_pid(running.lease_owner)
    assert owner_pid in worker.worker_pids()
    os.kill(owner_pid, signal.SIGKILL)

    job = wait_for_status(redis_settings, job_id, ("succeeded", "failed"))
    assert (job.status, job.attempts) == ("succeeded", 2), worker.log()
    # requeued once for its lost lease; under load the sweep may also send the requeued job's
    # message again (taken but not yet claimed for a lease's length: "enqueued again")
    requeued = [
        json.loads(line)
        for line in worker.log().splitlines()
        if line.startswith("{") and '"stage": "requeued"' in line and "lease expired" in line
    ]
    assert [line["job_id"] for line in requeued] == [job_id]


def test_upload_while_redis_is_down_is_accepted_and_runs_when_redis_returns(
    redis_settings: Settings,
    redis_server: RedisServer,
    worker_factory: Callable[..., WorkerProcess],
    caplog: pytest.LogCaptureFixture,
) -> None:
    worker = worker_factory(redis_settings)
    worker.wait_for_workers()
    with running_api(redis_settings) as api:
        client = api.client(api.token())
        site, _reference = site_with_reference(client)

        redis_server.stop()
        with caplog.at_level(logging.WARNING, logger="scandiff.jobs.queue"):
            response = upload(
                client, site["id"], ply_bytes(room_points(3000, seed=3)), method="pca"
            )
        assert response.status_code == 202, response.text
        job_id = response.json()["job"]["id"]
        assert client.get(f"/api/v1/jobs/{job_id}").json()["status"] == "queued"
        failed = [r for r in caplog.records if getattr(r, "stage", None) == "enqueue-failed"]
        assert [getattr(r, "job_id", None) for r in failed] == [job_id]
        assert "the queue is unreachable" in failed[0].getMessage()
        # due at the next sweep; a sweep of the worker's may be sending it right now (it marks
        # the job enqueued, fails against the stopped Redis, then clears the mark again)
        wait_until(
            lambda: load_job(redis_settings, job_id).enqueued_at is None,
            10.0,
            "the job left due for the next sweep while Redis is down",
        )

        health = client.get("/api/v1/health").json()
        assert health["queue"]["status"] == "error"  # said, not hidden

        redis_server.start()  # same port: the worker reconnects, its sweep sends the job
        job = wait_for_job(client, job_id)
    assert (job["status"], job["attempts"]) == ("succeeded", 1), worker.log()


def test_messages_lost_with_a_killed_redis_are_sent_again(
    redis_settings: Settings,
    redis_server: RedisServer,
    worker_factory: Callable[..., WorkerProcess],
) -> None:
    job_id = create_job(redis_settings)
    assert enqueue_job(job_id, redis_settings)
    assert get_huey(redis_settings).pending_count() == 1
    redis_server.kill()  # kill -9 without persistence: the message is gone
    redis_server.start()
    assert get_huey(redis_settings).pending_count() == 0

    worker = worker_factory(redis_settings)
    job = wait_for_status(redis_settings, job_id, ("succeeded", "failed"))
    assert (job.status, job.attempts) == ("succeeded", 1), worker.log()


def test_the_sweep_keeps_jobs_due_while_redis_is_down(
    redis_settings: Settings, redis_server: RedisServer
) -> None:
    job_ids = [create_job(redis_settings) for _ in range(3)]  # never enqueued: due at once
    redis_server.stop()

    report = recovery_sweep(redis_settings)  # must not raise

    assert sorted(report.unsent) == sorted(job_ids) and report.enqueued == []
    assert all(load_job(redis_settings, job_id).enqueued_at is None for job_id in job_ids)
    redis_server.start()
    report = recovery_sweep(redis_settings)
    assert sorted(report.enqueued) == sorted(job_ids) and report.unsent == []
    assert get_huey(redis_settings).pending_count() == 3
    assert QUEUE_NAME in get_huey(redis_settings).storage.queue_key
