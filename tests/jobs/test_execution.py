"""Claim, lease, results and failure handling of one job, in-process with the fake pipeline."""

from __future__ import annotations

import json
import time
from datetime import timedelta

import numpy as np
import pytest
from sqlalchemy import update

from app.clock import utc_now
from app.config import Settings
from app.db.models import Job
from app.db.session import transaction
from app.jobs.execution import execute_job
from app.jobs.hooks import job_hooks
from app.jobs.leases import (
    LeaseKeeper,
    LeaseLostError,
    claim_job,
    lease_owner_pid,
    make_lease_owner,
)
from app.jobs.queue import pending_job_ids
from app.jobs.results import store_results
from app.jobs.runner import run_job_once
from app.testing import fake_pipeline
from tests.helpers.jobs import count_regions, create_job, load_job


@pytest.fixture(autouse=True)
def fake_compare(monkeypatch: pytest.MonkeyPatch) -> None:
    """Use the fast deterministic pipeline stand-in."""
    monkeypatch.setattr(job_hooks, "compare", fake_pipeline.fake_compare)


def expire_lease(settings: Settings, job_id: str) -> None:
    """Make the job's lease look expired."""
    with transaction(settings.sqlalchemy_url) as session:
        session.execute(
            update(Job)
            .where(Job.id == job_id)
            .values(lease_expires_at=utc_now() - timedelta(seconds=1))
        )


def test_job_succeeds_with_results_regions_and_files(job_settings: Settings) -> None:
    job_id = create_job(job_settings)

    assert execute_job(job_id, job_settings) == "succeeded"

    job = load_job(job_settings, job_id)
    assert (job.status, job.attempts, job.progress, job.stage) == ("succeeded", 1, 1.0, "succeeded")
    assert job.changed is True and job.n_regions == 1 and count_regions(job_settings, job_id) == 1
    assert job.labels_path == f"results/{job_id}/labels.npz"
    assert job.registration["rmse"] is None  # non-finite numbers stored as null (portable JSON)
    assert {name: job.calibration[name] for name in ("noise", "samples")} == {
        "noise": 0.001,  # numpy values stored as JSON numbers
        "samples": [0, 1, 2],
    }
    assert job.effective_params == {"variant": "improved", "random_state": 0}
    assert {"align", "load_inputs", "write_outputs", "job_total"} <= set(job.timings)
    results = job_settings.results_dir / job_id
    with np.load(results / "labels.npz") as labels, np.load(results / "details.npz") as details:
        assert set(labels.files) == {
            "reference_changed",
            "scan_changed",
            "reference_label",
            "scan_label",
        }
        assert details["scan_distance"].dtype == np.float32
        assert details["reference_distance"].shape == labels["reference_label"].shape
    assert sorted(path.name for path in results.iterdir()) == ["details.npz", "labels.npz"]


def test_duplicate_messages_run_the_job_once(job_settings: Settings) -> None:
    job_id = create_job(job_settings)

    outcomes = [execute_job(job_id, job_settings) for _ in range(4)]

    assert outcomes == ["succeeded", "skipped", "skipped", "skipped"]
    job = load_job(job_settings, job_id)
    assert job.attempts == 1 and count_regions(job_settings, job_id) == 1


def test_claim_is_exclusive_while_the_lease_is_live(job_settings: Settings) -> None:
    job_id = create_job(job_settings)
    first = claim_job(job_id, job_settings, make_lease_owner())

    assert first is not None and first.attempt == 1
    assert claim_job(job_id, job_settings, make_lease_owner()) is None
    job = load_job(job_settings, job_id)
    assert (job.status, job.attempts, job.lease_owner) == ("running", 1, first.lease_owner)
    assert lease_owner_pid(job.lease_owner) is not None


def test_a_claim_that_waited_for_the_write_lock_gets_a_whole_lease(job_settings: Settings) -> None:
    """The lease runs from when the claim holds the database, not from when it asked: a worker
    that waited behind another writer for longer than a lease must not get an expired one (the
    recovery sweep would requeue the job at once and a second worker run it)."""
    import sqlite3
    import threading

    settings = job_settings.model_copy(update={"job_lease_seconds": 1.0})
    job_id = create_job(settings)
    blocker = sqlite3.connect(settings.data_layout.database_file, timeout=5)
    blocker.execute("BEGIN IMMEDIATE")  # another writer holds the lock for 1.5 leases
    claims: list[object] = []
    claimer = threading.Thread(
        target=lambda: claims.append(claim_job(job_id, settings, make_lease_owner()))
    )
    claimer.start()
    time.sleep(1.5)
    released_at = utc_now()
    blocker.rollback()
    blocker.close()
    claimer.join(30)
    assert claims and claims[0] is not None
    job = load_job(settings, job_id)
    lease_expires_at = job.lease_expires_at.replace(tzinfo=released_at.tzinfo)  # stored in UTC
    assert lease_expires_at >= released_at + timedelta(seconds=0.9), (
        "the lease was dated from before the claim held the database"
    )


def test_expired_lease_is_taken_over_and_the_old_owner_cannot_store(
    job_settings: Settings,
) -> None:
    job_id = create_job(job_settings)
    stale = claim_job(job_id, job_settings, make_lease_owner())
    assert stale is not None
    expire_lease(job_settings, job_id)

    assert execute_job(job_id, job_settings) == "succeeded"
    assert not store_results(stale, job_settings, object(), "x", {})  # lease no longer ours
    job = load_job(job_settings, job_id)
    assert (job.status, job.attempts) == ("succeeded", 2)
    assert count_regions(job_settings, job_id) == 1


def test_attempts_used_up_fail_the_job_with_a_reason(job_settings: Settings) -> None:
    job_id = create_job(job_settings, max_attempts=2)
    for _ in range(2):
        assert claim_job(job_id, job_settings, make_lease_owner()) is not None
        expire_lease(job_settings, job_id)

    assert execute_job(job_id, job_settings) == "skipped"

    job = load_job(job_settings, job_id)
    assert (job.status, job.attempts) == ("failed", 2)
    assert "gave up after 2 attempts" in job.error


def test_input_error_fails_at_once_with_the_message(job_settings: Settings) -> None:
    job_id = create_job(job_settings, scan_bytes=b"not a point cloud")

    assert execute_job(job_id, job_settings) == "failed"

    job = load_job(job_settings, job_id)
    assert (job.status, job.attempts) == ("failed", 1)
    assert job.error and "npy" in job.error.lower()
    assert pending_job_ids(job_settings) == set()


def test_transient_errors_are_retried_then_fail_after_max_attempts(
    job_settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("SCANDIFF_TESTING", "1")
    monkeypatch.setenv(
        "SCANDIFF_TEST_JOB_HOOKS", json.dumps({"raise_error": "disk on fire", "on_attempts": [1]})
    )
    job_id = create_job(job_settings)

    assert run_job_once(job_id, job_settings) == "queued"
    job = load_job(job_settings, job_id)
    assert job.status == "queued" and "disk on fire" in job.error
    assert job_id in pending_job_ids(job_settings)  # sent again at once
    assert run_job_once(job_id, job_settings) == "succeeded"
    assert load_job(job_settings, job_id).attempts == 2

    monkeypatch.setenv("SCANDIFF_TEST_JOB_HOOKS", json.dumps({"raise_error": "always"}))
    poison_id = create_job(job_settings)
    outcomes = [run_job_once(poison_id, job_settings) for _ in range(4)]
    assert outcomes == ["queued", "queued", "failed", "skipped"]
    job = load_job(job_settings, poison_id)
    assert (job.status, job.attempts) == ("failed", 3)
    assert job.error == "failed after 3 attempts; last error: RuntimeError: always"


def test_test_hooks_are_ignored_unless_testing_is_enabled(
    job_settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("SCANDIFF_TESTING", raising=False)
    monkeypatch.setenv("SCANDIFF_TEST_JOB_HOOKS", json.dumps({"kill_worker": True}))
    job_id = create_job(job_settings)

    assert execute_job(job_id, job_settings) == "succeeded"


def test_shutdown_interrupt_hands_the_job_back_without_using_an_attempt(
    job_settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    def interrupted(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(job_hooks, "compare", interrupted)
    job_id = create_job(job_settings)

    with pytest.raises(KeyboardInterrupt):
        execute_job(job_id, job_settings)

    job = load_job(job_settings, job_id)
    assert (job.status, job.attempts, job.lease_owner, job.enqueued_at) == ("queued", 0, None, None)


def test_heartbeat_extends_the_lease_and_notices_a_takeover(job_settings: Settings) -> None:
    job_id = create_job(job_settings)
    job = claim_job(job_id, job_settings, make_lease_owner())
    assert job is not None
    first_expiry = load_job(job_settings, job_id).lease_expires_at
    keeper = LeaseKeeper(job, job_settings).start()
    try:
        keeper.report("align", 0.3)
        time.sleep(job_settings.job_heartbeat_seconds * 3)
        row = load_job(job_settings, job_id)
        assert row.lease_expires_at > first_expiry
        assert (row.stage, row.progress) == ("align", 0.3)

        expire_lease(job_settings, job_id)
        assert claim_job(job_id, job_settings, make_lease_owner()) is not None  # taken over
        assert keeper.lost.wait(5.0)
        with pytest.raises(LeaseLostError):
            keeper.report("detect", 0.6)
    finally:
        keeper.stop()


def test_sensor_origins_stored_with_the_scans_reach_compare(
    job_settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    from app.db.models import Scan

    seen: dict[str, object] = {}

    def recording_compare(reference, scan, **keywords):  # type: ignore[no-untyped-def]
        seen["reference"] = reference.sensor_origin
        seen["scan"] = scan.sensor_origin
        return fake_pipeline.fake_compare(reference, scan, **keywords)

    monkeypatch.setattr(job_hooks, "compare", recording_compare)
    job_id = create_job(job_settings)
    with transaction(job_settings.sqlalchemy_url) as session:
        job = session.get(Job, job_id)
        session.get(Scan, job.reference_scan_id).sensor_origin = [1.0, 2.0, 3.0]
        session.get(Scan, job.scan_id).sensor_origin = [[0.0, 0.0, 0.5], [4.0, 1.0, 1.5]]

    assert execute_job(job_id, job_settings) == "succeeded"
    np.testing.assert_array_equal(seen["reference"], [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(seen["scan"], [[0.0, 0.0, 0.5], [4.0, 1.0, 1.5]])  # stations
