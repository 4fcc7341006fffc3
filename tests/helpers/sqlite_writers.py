"""Writers for the SQLite contention test, run in spawned processes: this module imports only
the settings, the models and the job leases/queue/sweep (not the app), so each process starts in
a fraction of a second instead of seconds."""

from __future__ import annotations

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
from tests.helpers.job_rows import new_job

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
