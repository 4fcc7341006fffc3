"""``scandiff worker`` and ``scandiff serve --workers 0`` as real processes.

The worker never migrates: it waits, saying so, for a database at head, and gives up with one
clear line when told to wait no longer.  SIGTERM stops it with exit status 0: a running job
finishes within the grace, or is handed back without using an attempt and another worker runs
it.  ``serve --workers 0`` serves the API without any job worker.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path

from app.config import Settings
from app.db.migrate import upgrade_to_head
from app.jobs.queue import enqueue_job
from app.testing.files import ply_bytes
from app.testing.scenes import room_points
from app.testing.service import ServiceProcess
from app.testing.waiting import wait_until
from tests.helpers.http import site_with_reference, upload_accepted
from tests.helpers.jobs import FAST_LEASES, create_job, load_job, wait_for_status
from tests.helpers.worker import WorkerProcess


def hooks_env(**hooks: object) -> dict[str, str]:
    """Environment enabling the job test hooks ``hooks``."""
    return {"SCANDIFF_TESTING": "1", "SCANDIFF_TEST_JOB_HOOKS": json.dumps(hooks)}


def test_worker_waits_for_a_migrated_database_then_runs_jobs(
    tmp_path: Path, worker_factory: Callable[..., WorkerProcess]
) -> None:
    settings = Settings(data_dir=tmp_path / "data", **FAST_LEASES)
    settings.data_dir.mkdir()
    worker = worker_factory(settings, concurrency=2)

    wait_until(lambda: "waiting for the database" in worker.log(), 30, "the wait is logged")
    assert "never migrated" in worker.log() and "scandiff serve" in worker.log()
    assert worker.process.poll() is None and worker.worker_pids() == []

    upgrade_to_head(settings.sqlalchemy_url)  # what the API process does at start
    worker.wait_for_workers()
    job_id = create_job(settings)
    enqueue_job(job_id, settings)
    job = wait_for_status(settings, job_id, ("succeeded", "failed"))
    assert (job.status, job.attempts) == ("succeeded", 1), worker.log()


def test_worker_gives_up_on_an_unmigrated_database_with_one_clear_line(
    tmp_path: Path, worker_factory: Callable[..., WorkerProcess]
) -> None:
    settings = Settings(data_dir=tmp_path / "data")
    settings.data_dir.mkdir()
    worker = worker_factory(settings, arguments=["--wait-for-database", "1"])

    assert worker.process.wait(30) == 1
    last_line = worker.log().strip().splitlines()[-1]
    assert last_line.startswith("scandiff worker: error: gave up after waiting 1 s"), last_line
    assert "never migrated" in last_line and "alembic upgrade head" in last_line


def test_worker_rejects_a_bad_concurrency_with_a_message(
    job_settings: Settings, worker_factory: Callable[..., WorkerProcess]
) -> None:
    worker = worker_factory(job_settings, concurrency=0)

    assert worker.process.wait(30) == 2
    assert "--concurrency: '0': give a whole number of processes >= 1" in worker.log()


def test_sigterm_lets_a_running_job_finish_within_the_grace(
    job_settings: Settings, worker_factory: Callable[..., WorkerProcess]
) -> None:
    worker = worker_factory(
        job_settings,
        arguments=["--shutdown-grace", "30"],
        env=hooks_env(sleep_seconds=2.0),
    )
    worker.wait_for_workers()
    job_id = create_job(job_settings)
    enqueue_job(job_id, job_settings)
    wait_for_status(job_settings, job_id, ("running",))

    started = time.monotonic()
    assert worker.terminate(timeout=30) == 0, worker.log()
    stopped_after = time.monotonic() - started

    job = load_job(job_settings, job_id)
    assert (job.status, job.attempts, job.error) == ("succeeded", 1, None), worker.log()
    assert stopped_after < 20, stopped_after  # it finished its job, it did not sit out the grace
    assert worker.worker_pids() == []


def test_sigterm_past_the_grace_hands_the_job_to_another_worker_without_an_attempt(
    job_settings: Settings, worker_factory: Callable[..., WorkerProcess]
) -> None:
    first = worker_factory(
        job_settings,
        env={
            "SCANDIFF_SHUTDOWN_GRACE_SECONDS": "1",
            **hooks_env(sleep_seconds=60, on_attempts=[1]),
        },
    )
    first.wait_for_workers()
    job_id = create_job(job_settings)
    enqueue_job(job_id, job_settings)
    wait_for_status(job_settings, job_id, ("running",))
    second = worker_factory(job_settings)
    second.wait_for_workers()

    assert first.terminate(timeout=30) == 0, first.log()
    handed_back = json.loads(
        next(line for line in first.log().splitlines() if "interrupted by a worker" in line)
    )
    assert handed_back["job_id"] == job_id

    job = wait_for_status(job_settings, job_id, ("succeeded", "failed"))
    assert (job.status, job.attempts) == ("succeeded", 1), second.log()
    assert job_id in second.log()


def test_serve_with_zero_workers_runs_the_api_only_and_a_worker_runs_its_jobs(
    service_factory: Callable[..., ServiceProcess], worker_factory: Callable[..., WorkerProcess]
) -> None:
    service = service_factory(workers=0, env={"SCANDIFF_RECOVERY_INTERVAL_SECONDS": "0.5"})
    assert "no job workers here (--workers 0)" in service.log_text()
    with service.client() as client:
        site, _reference = site_with_reference(client)
        scan = upload_accepted(client, site["id"], "scan.ply", ply_bytes(room_points(3000, seed=2)))
        job_id = scan["job"]["id"]
        time.sleep(1.0)
        assert client.get(f"/api/v1/jobs/{job_id}").json()["status"] == "queued"
        assert service.worker_pids() == []

        worker = worker_factory(Settings(data_dir=service.data_dir, **FAST_LEASES))
        job = service.wait_for_job(client, job_id, timeout=60)
    assert job["status"] == "succeeded", worker.log()
