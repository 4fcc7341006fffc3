"""The recovery sweep and the queue helpers, in-process on a migrated database."""

from __future__ import annotations

import os
import socket
import subprocess
import time
from datetime import timedelta

import pytest
from sqlalchemy import update

from app.clock import utc_now
from app.config import Settings
from app.db.models import Job
from app.db.session import transaction
from app.jobs.leases import claim_job, make_lease_owner
from app.jobs.queue import (
    enqueue_job,
    get_huey,
    pending_job_ids,
    queue_backend,
    queue_health,
    send_job_message,
)
from app.jobs.recovery import recovery_sweep
from tests.helpers.jobs import create_job, load_job


def set_job(settings: Settings, job_id: str, **values: object) -> None:
    """Overwrite columns of a job row."""
    with transaction(settings.sqlalchemy_url) as session:
        session.execute(update(Job).where(Job.id == job_id).values(**values))


def test_enqueue_job_notes_the_time_and_sends_one_message(job_settings: Settings) -> None:
    job_id = create_job(job_settings)

    enqueue_job(job_id, job_settings)

    assert load_job(job_settings, job_id).enqueued_at is not None
    assert pending_job_ids(job_settings) == {job_id}
    health = queue_health(job_settings)
    assert (health["status"], health["backend"], health["pending"]) == ("ok", "sqlite", 1)
    assert job_settings.queue_path.is_file()


def test_sweep_requeues_expired_leases_and_fails_used_up_jobs(job_settings: Settings) -> None:
    lost_id, poison_id, live_id = (create_job(job_settings) for _ in range(3))
    for job_id in (lost_id, poison_id, live_id):
        assert claim_job(job_id, job_settings, make_lease_owner()) is not None
    expired = utc_now() - timedelta(seconds=1)
    set_job(job_settings, lost_id, lease_expires_at=expired)
    set_job(job_settings, poison_id, lease_expires_at=expired, attempts=3, stage="detect")

    report = recovery_sweep(job_settings)

    assert report.requeued_expired == [lost_id] and report.failed_expired == [poison_id]
    lost = load_job(job_settings, lost_id)
    assert (lost.status, lost.lease_owner, lost.attempts) == ("queued", None, 1)
    assert "attempt 1 stopped without finishing" in lost.error
    poison = load_job(job_settings, poison_id)
    assert poison.status == "failed" and poison.finished_at is not None
    assert poison.error.startswith("gave up after 3 attempts (max_attempts=3)")
    assert "stage detect" in poison.error
    assert load_job(job_settings, live_id).status == "running"
    assert pending_job_ids(job_settings) == {lost_id}


def test_sweep_requeues_at_once_a_job_whose_local_worker_is_gone(job_settings: Settings) -> None:
    finished = subprocess.Popen(["true"])
    finished.wait()  # reaped: its pid no longer exists
    dead_pid = finished.pid
    job_id = create_job(job_settings)
    dead_owner = f"{socket.gethostname()}:{dead_pid}:deadbeef"
    assert claim_job(job_id, job_settings, dead_owner) is not None  # lease still 2 s ahead

    report = recovery_sweep(job_settings)

    assert report.requeued_expired == [job_id]
    job = load_job(job_settings, job_id)
    assert job.status == "queued" and "its worker process is gone" in job.error


def test_sweep_resends_queued_jobs_without_a_live_message(job_settings: Settings) -> None:
    # a minute's grace: with the fast 2 s lease, "just sent" outlived it between the two sweeps
    # on a loaded machine and was (rightly) sent again
    job_settings = job_settings.model_copy(update={"job_lease_seconds": 60.0})
    never_sent = create_job(job_settings)
    message_lost = create_job(job_settings)
    still_waiting = create_job(job_settings)
    just_sent = create_job(job_settings)
    long_ago = utc_now() - timedelta(seconds=job_settings.job_lease_seconds + 5)
    set_job(job_settings, message_lost, enqueued_at=long_ago)
    set_job(job_settings, still_waiting, enqueued_at=long_ago)
    send_job_message(still_waiting, job_settings)
    set_job(job_settings, just_sent, enqueued_at=utc_now())

    report = recovery_sweep(job_settings)

    assert sorted(report.resent_queued) == sorted([never_sent, message_lost])
    assert pending_job_ids(job_settings) == {never_sent, message_lost, still_waiting}
    assert len(get_huey(job_settings).pending()) == 3  # no duplicate for still_waiting
    assert recovery_sweep(job_settings).is_empty()  # a second sweep finds nothing to do


def test_sweep_removes_stale_temporary_result_files(job_settings: Settings) -> None:
    directory = job_settings.results_dir / "somejob"
    directory.mkdir(parents=True)
    stale = directory / ".labels.0123.tmp.npz"
    fresh = directory / ".labels.4567.tmp.npz"
    kept = directory / "labels.npz"
    for path in (stale, fresh, kept):
        path.write_bytes(b"x")
    an_hour_ago = time.time() - 3700
    os.utime(stale, (an_hour_ago, an_hour_ago))

    assert recovery_sweep(job_settings).removed_temp_files == 1
    assert not stale.exists() and fresh.exists() and kept.exists()


def test_sweep_removes_tile_inputs_of_jobs_that_no_longer_run(job_settings: Settings) -> None:
    # a worker killed between storing a tiled job's labels and deleting its crops leaves them
    statuses = ["succeeded", "failed", "queued", "running"]
    job_ids = [create_job(job_settings) for _ in statuses]
    for job_id, status in zip(job_ids, statuses, strict=True):
        set_job(job_settings, job_id, status=status)
    tiles = [job_settings.data_layout.job_tiles_dir(job_id) for job_id in job_ids]
    tiles.append(job_settings.data_layout.job_tiles_dir("deletedjob"))
    for directory in tiles:
        (directory / "crops").mkdir(parents=True)
        (directory / "crops" / "reference-0.bin").write_bytes(b"x" * 64)
    labels = job_settings.data_layout.labels_file(job_ids[0])
    labels.write_bytes(b"kept")

    assert recovery_sweep(job_settings).removed_tile_inputs == 3
    assert [directory.exists() for directory in tiles] == [False, False, True, True, False]
    assert labels.read_bytes() == b"kept"  # the stored results stay
    assert recovery_sweep(job_settings).is_empty()


def test_queue_backend_follows_the_queue_url(tmp_path: object) -> None:
    assert queue_backend(Settings(data_dir=tmp_path)) == "sqlite"
    assert queue_backend(Settings(data_dir=tmp_path, queue_url="redis://localhost:6379/0")) == (
        "redis"
    )
    with pytest.raises(ValueError, match="unsupported SCANDIFF_QUEUE_URL"):
        queue_backend(Settings(data_dir=tmp_path, queue_url="amqp://localhost"))
