"""Heartbeats, API-style writes and recovery sweeps from several processes never hit a lock error.

Each writer is a separate process hammering the same migrated SQLite file as fast as it can for
a few seconds: heart-beating leases, creating jobs the way the API does (read, then write, in one
transaction, then enqueue) and sweeping.  With WAL, a long busy timeout and ``BEGIN IMMEDIATE``
none of them may see "database is locked" (DESIGN.md measured thousands per second without).
"""

from __future__ import annotations

import multiprocessing
import os
import time
from typing import Any

from sqlalchemy import select

from app.config import Settings
from app.db.models import Job, Site
from app.db.session import session_factory
from app.jobs.leases import ClaimedJob, LeaseKeeper, claim_job, make_lease_owner
from app.jobs.queue import enqueue_job
from app.jobs.recovery import recovery_sweep
from tests.helpers.jobs import create_job, new_job

DURATION_SECONDS = 1.5


def hammer(role: str, settings_kwargs: dict[str, Any], job_ids: list[str], results: Any) -> None:
    """Write as fast as possible as ``role`` for DURATION_SECONDS; report (role, ops, errors)."""
    settings = Settings(**settings_kwargs)
    operations, errors = 0, []
    keepers = []
    if role == "heartbeat":
        for job_id in job_ids:
            job = claim_job(job_id, settings, make_lease_owner())
            assert isinstance(job, ClaimedJob)
            keepers.append(LeaseKeeper(job, settings))
    deadline = time.monotonic() + DURATION_SECONDS
    while time.monotonic() < deadline:
        try:
            if role == "heartbeat":
                for keeper in keepers:
                    keeper.progress = (operations % 100) / 100
                    assert keeper.beat()
                    operations += 1
            elif role == "api":
                session = session_factory(settings.sqlalchemy_url)()
                with session.begin():  # read first, write later: the upgrade that used to fail
                    site = session.scalars(select(Site).limit(1)).one()
                    template = session.scalars(select(Job).limit(1)).one()
                    job = new_job(
                        site,
                        template.reference_scan_id,
                        template.scan_id,
                        params={},
                        status="failed",  # not for the workers
                    )
                    session.add(job)
                    site.description = f"write {operations}"
                session.close()
                enqueue_job(job.id, settings)
                operations += 1
            else:
                recovery_sweep(settings)
                operations += 1
        except Exception as exc:
            errors.append(f"{type(exc).__name__}: {exc}")
    results.put((role, os.getpid(), operations, errors[:5], len(errors)))


def test_concurrent_writers_never_see_database_is_locked(job_settings: Settings) -> None:
    job_ids = [create_job(job_settings, n_points=50) for _ in range(4)]
    settings_kwargs = {
        "data_dir": job_settings.data_dir,
        "job_lease_seconds": 30.0,  # nothing expires: the sweep only reads and re-sends
    }
    context = multiprocessing.get_context("spawn")
    results = context.Queue()
    roles = [("heartbeat", job_ids[:2]), ("heartbeat", job_ids[2:]), ("api", []), ("sweep", [])]
    processes = [
        context.Process(target=hammer, args=(role, settings_kwargs, ids, results))
        for role, ids in roles
    ]
    for process in processes:
        process.start()
    reports = [results.get(timeout=60) for _ in processes]
    for process in processes:
        process.join(10)

    summary = {f"{role}-{pid}": operations for role, pid, operations, _, _ in reports}
    print(f"\nwrites in {DURATION_SECONDS}s per process: {summary}")
    for role, _pid, operations, sample, n_errors in reports:
        assert n_errors == 0, f"{role}: {n_errors} errors, e.g. {sample}"
        assert operations > 0, f"{role} made no progress"
