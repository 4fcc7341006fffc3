"""Durability against real consumer processes: kills, poison jobs, duplicate messages.

The consumer runs as ``python -m app.jobs.consumer`` would (Huey process workers, recovery sweep
in the supervisor) with short leases and the fast pipeline stand-in, on a database migrated with
Alembic.  Recovery times are printed (``pytest -s``) and bounded.
"""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import time
from collections.abc import Callable
from pathlib import Path

from app.config import Settings
from app.jobs.leases import lease_owner_pid
from app.jobs.queue import enqueue_job, get_huey, send_job_message
from app.testing.service import ConsumerProcess
from tests.helpers.jobs import count_regions, create_job, load_job, wait_for_status


def hooks_env(**hooks: object) -> dict[str, str]:
    """Environment enabling the job test hooks ``hooks``."""
    return {"SCANDIFF_TESTING": "1", "SCANDIFF_TEST_JOB_HOOKS": json.dumps(hooks)}


def freeze_outside_a_write(pid: int, settings: Settings, attempts: int = 50) -> None:
    """SIGSTOP ``pid`` at a moment it holds no SQLite write lock.

    A process stopped inside a write transaction keeps SQLite's file lock, and every writer waits
    for it (SQLite cannot break a live process's lock: a limit of the embedded default, see
    docs/jobs.md, "Failures").  This test is about the lease, so it freezes the worker between
    its heartbeat writes: stop, probe the write lock, and on a miss let it run and try again.
    """
    database = settings.data_layout.database_file
    for _ in range(attempts):
        os.kill(pid, signal.SIGSTOP)
        probe = sqlite3.connect(database, timeout=0.2)
        try:
            probe.execute("BEGIN IMMEDIATE")
            probe.rollback()
            return
        except sqlite3.OperationalError:
            os.kill(pid, signal.SIGCONT)
            time.sleep(0.01)
        finally:
            probe.close()
    raise AssertionError(f"worker {pid} held the write lock at every one of {attempts} tries")


def test_consumer_runs_an_enqueued_job(
    job_settings: Settings, consumer_factory: Callable[..., ConsumerProcess]
) -> None:
    consumer = consumer_factory(workers=1)
    job_id = create_job(job_settings)

    enqueue_job(job_id, job_settings)
    job = wait_for_status(job_settings, job_id, ("succeeded", "failed"))

    assert (job.status, job.attempts, job.error) == ("succeeded", 1, None), consumer.log()
    assert count_regions(job_settings, job_id) == job.n_regions == 1
    assert (job_settings.results_dir / job_id / "labels.npz").is_file()
    assert (job_settings.results_dir / job_id / "details.npz").is_file()
    expected_stages = {"claimed", "loading", "comparing", "writing", "storing", "succeeded"}
    deadline = time.monotonic() + 10.0  # the last line is logged just after the commit
    while True:
        stages = {
            json.loads(line).get("stage")
            for line in consumer.log().splitlines()
            if line.startswith("{") and job_id in line
        }
        if expected_stages <= stages or time.monotonic() > deadline:
            break
        time.sleep(0.1)
    assert expected_stages <= stages


def test_worker_killed_mid_job_is_finished_by_another_attempt(
    job_settings: Settings, consumer_factory: Callable[..., ConsumerProcess]
) -> None:
    consumer = consumer_factory(workers=2, env=hooks_env(sleep_seconds=60, on_attempts=[1]))
    consumer.wait_for_workers()
    job_id = create_job(job_settings)
    enqueue_job(job_id, job_settings)
    running = wait_for_status(job_settings, job_id, ("running",))
    while load_job(job_settings, job_id).stage != "testing-sleep":
        time.sleep(0.02)

    os.kill(lease_owner_pid(running.lease_owner), signal.SIGKILL)
    killed_at = time.monotonic()
    second = wait_for_status(job_settings, job_id, ("succeeded", "failed"), timeout=30)
    recovery_seconds = time.monotonic() - killed_at

    print(f"\nkilled worker's job finished by attempt 2 in {recovery_seconds:.2f}s")
    assert (second.status, second.attempts) == ("succeeded", 2), consumer.log()
    assert lease_owner_pid(second.lease_owner) != lease_owner_pid(running.lease_owner)
    assert count_regions(job_settings, job_id) == 1
    # the sweep sees the local worker is gone (0.5 s interval) without waiting for the lease;
    # generous bound for a loaded machine
    assert recovery_seconds < job_settings.job_lease_seconds + 6
    assert len(consumer.wait_for_workers()) == 2  # the dead worker was replaced


def test_frozen_worker_loses_its_lease_and_cannot_store_after_waking(
    job_settings: Settings, consumer_factory: Callable[..., ConsumerProcess]
) -> None:
    consumer = consumer_factory(workers=2, env=hooks_env(sleep_seconds=4, on_attempts=[1]))
    consumer.wait_for_workers()
    job_id = create_job(job_settings)
    enqueue_job(job_id, job_settings)
    running = wait_for_status(job_settings, job_id, ("running",))
    frozen_pid = lease_owner_pid(running.lease_owner)

    freeze_outside_a_write(frozen_pid, job_settings)  # alive but silent: only the lease can tell
    frozen_at = time.monotonic()
    try:
        second = wait_for_status(job_settings, job_id, ("succeeded", "failed"), timeout=30)
        takeover_seconds = time.monotonic() - frozen_at
    finally:
        os.kill(frozen_pid, signal.SIGCONT)
    deadline = time.monotonic() + 15
    while "lease lost" not in consumer.log() and time.monotonic() < deadline:
        time.sleep(0.1)

    print(f"\nfrozen worker's job taken over and finished in {takeover_seconds:.2f}s")
    assert (second.status, second.attempts) == ("succeeded", 2), consumer.log()
    assert takeover_seconds >= job_settings.job_lease_seconds - 0.5  # waited for the lease
    assert "lease lost" in consumer.log()
    time.sleep(0.5)
    job = load_job(job_settings, job_id)
    assert (job.status, job.attempts, job.lease_owner) == (
        "succeeded",
        2,
        second.lease_owner,
    )
    assert count_regions(job_settings, job_id) == 1


def test_poison_job_fails_after_max_attempts_and_others_still_run(
    job_settings: Settings, consumer_factory: Callable[..., ConsumerProcess]
) -> None:
    consumer = consumer_factory(
        workers=2, env=hooks_env(kill_worker=True, scan_filename="poison.npy")
    )
    poison_id = create_job(job_settings, scan_filename="poison.npy")
    healthy_id = create_job(job_settings)
    started = time.monotonic()
    enqueue_job(poison_id, job_settings)
    enqueue_job(healthy_id, job_settings)

    poison = wait_for_status(job_settings, poison_id, ("succeeded", "failed"), timeout=45)
    print(
        f"\npoison job failed after {poison.attempts} attempts, {time.monotonic() - started:.1f}s"
    )

    assert (poison.status, poison.attempts) == ("failed", job_settings.job_max_attempts)
    assert poison.error.startswith("gave up after 3 attempts"), poison.error
    assert "worker killed or lost" in poison.error
    healthy = wait_for_status(job_settings, healthy_id, ("succeeded", "failed"))
    assert healthy.status == "succeeded", consumer.log()


def test_sigterm_hands_a_running_job_back_without_using_an_attempt(
    job_settings: Settings, consumer_factory: Callable[..., ConsumerProcess]
) -> None:
    consumer = consumer_factory(
        workers=1, env=hooks_env(sleep_seconds=60, on_attempts=[1]), shutdown_grace_seconds=1.0
    )
    job_id = create_job(job_settings)
    enqueue_job(job_id, job_settings)
    wait_for_status(job_settings, job_id, ("running",))

    assert consumer.stop(timeout=20) == 0
    assert consumer.worker_pids() == []
    job = load_job(job_settings, job_id)
    assert (job.status, job.attempts, job.lease_owner, job.enqueued_at) == ("queued", 0, None, None)
    assert job.error == "interrupted by a worker shutdown"

    consumer_factory(workers=1)  # the next consumer's first sweep sends it again
    job = wait_for_status(job_settings, job_id, ("succeeded", "failed"))
    assert (job.status, job.attempts) == ("succeeded", 1)


def test_duplicate_messages_run_the_job_once(
    job_settings: Settings, consumer_factory: Callable[..., ConsumerProcess]
) -> None:
    job_id = create_job(job_settings)
    enqueue_job(job_id, job_settings)
    for _ in range(5):
        send_job_message(job_id, job_settings)
    assert get_huey(job_settings).pending_count() == 6

    consumer = consumer_factory(workers=2)
    job = wait_for_status(job_settings, job_id, ("succeeded", "failed"))
    deadline = time.monotonic() + 10
    while get_huey(job_settings).pending_count() and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.3)  # let the last duplicates finish being ignored

    job = load_job(job_settings, job_id)
    assert (job.status, job.attempts) == ("succeeded", 1), consumer.log()
    assert count_regions(job_settings, job_id) == 1
    assert consumer.log().count('"stage": "claimed"') == 1


def test_memory_cap_fails_a_job_that_needs_too_much_and_spares_the_others(
    tmp_path: Path, job_settings: Settings
) -> None:
    capped = job_settings.model_copy(update={"job_memory_limit_bytes": 1_000_000_000})
    consumer = ConsumerProcess(
        capped,
        workers=1,
        env=hooks_env(allocate_bytes=3_000_000_000, scan_filename="huge.npy"),
        log_path=tmp_path / "capped.log",
    )
    try:
        huge_id = create_job(capped, scan_filename="huge.npy")
        normal_id = create_job(capped)
        enqueue_job(huge_id, capped)
        enqueue_job(normal_id, capped)

        huge = wait_for_status(capped, huge_id, ("succeeded", "failed"))
        normal = wait_for_status(capped, normal_id, ("succeeded", "failed"))
    finally:
        consumer.stop()

    assert (huge.status, huge.attempts) == ("failed", 1), consumer.log()
    assert huge.error.startswith("out of memory") and "1000000000" in huge.error
    assert normal.status == "succeeded", consumer.log()
