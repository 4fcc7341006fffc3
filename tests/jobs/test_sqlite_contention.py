"""Heartbeats, API-style writes and recovery sweeps from several processes never hit a lock error.

Each writer is a separate process hammering the same migrated SQLite file as fast as it can for
a few seconds: heart-beating leases, creating jobs the way the API does (read, then write, in one
transaction, then enqueue) and sweeping.  With WAL, a long busy timeout and ``BEGIN IMMEDIATE``
none of them may see "database is locked" (DESIGN.md measured thousands per second without).
"""

from __future__ import annotations

import multiprocessing

from app.config import Settings
from tests.helpers.jobs import create_job
from tests.helpers.sqlite_writers import DURATION_SECONDS, hammer


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
