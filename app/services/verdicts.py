"""Review verdicts on finished jobs, and the per-site thresholds learned from them.

A reviewer marks a succeeded job ``confirmed``, ``false_alarm`` or ``new_reference`` (the
job's scan becomes the site's reference, recorded in the reference history).  A later verdict
replaces the current one (``job.verdict``); every verdict stays in ``job_verdict`` with who
(the API token) and when.  Each verdict recomputes the site's calibration
(:func:`app.core.site_calibration.learn_site_calibration`) from its *reviewed-null* jobs: the
current verdict is ``false_alarm``, or ``confirmed`` on a job that decided unchanged.  The
worker passes it to the next comparisons of the site (:mod:`app.jobs.execution`).
"""

from __future__ import annotations

from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.clock import utc_now
from app.config import Settings
from app.db.models import ApiToken, Job, JobStatus, JobVerdict, Scan
from app.services import jobs, sites
from app.services.auth import Principal
from app.services.errors import ConflictError
from app.services.paging import newest_first_page
from app.services.schemas import VerdictCreate
from app.services.site_calibration import recompute_site_calibration


def set_verdict(
    session: Session, settings: Settings, principal: Principal, job_id: str, payload: VerdictCreate
) -> Job:
    """Record a reviewer's verdict on a succeeded job (409 otherwise); the job."""
    job = jobs.get_job(session, principal, job_id)
    if job.status != JobStatus.SUCCEEDED:
        raise ConflictError(
            f"job {job.id} is {job.status}; only a succeeded job can get a verdict "
            "(wait until it has finished, or re-run a failed one with POST /api/v1/jobs)",
            code="job_not_succeeded",
        )
    site = sites.get_site(session, principal, job.site_id)
    if payload.verdict == "new_reference":
        scan = session.get(Scan, job.scan_id)
        if scan is None:
            raise ConflictError(f"the scan of job {job.id} no longer exists", code="scan_missing")
        sites.set_reference(session, site, scan)
    token = session.get(ApiToken, principal.token_id)
    now = utc_now()
    record = JobVerdict(
        organisation_id=principal.organisation_id,
        site_id=site.id,
        job_id=job.id,
        verdict=payload.verdict,
        note=payload.note or None,
        token_id=principal.token_id,
        token_name=token.name if token is not None else None,
        role=principal.role,
        created_at=now,
    )
    session.add(record)
    job.verdict = verdict_json(record)
    session.flush()
    recompute_site_calibration(session, settings, site)
    return job


def verdict_json(record: JobVerdict) -> dict[str, Any]:
    """The ``job.verdict`` form of a verdict row."""
    return {
        "verdict": record.verdict,
        "note": record.note,
        "set_by": {"token_id": record.token_id, "name": record.token_name, "role": record.role},
        "set_at": record.created_at.isoformat(),
    }


def list_verdicts(
    session: Session, principal: Principal, job_id: str, limit: int, cursor: str | None
) -> tuple[list[dict[str, Any]], str | None]:
    """The verdicts given to a job, newest first (the ``job.verdict`` form); one page."""
    job = jobs.get_job(session, principal, job_id)
    rows, next_cursor = newest_first_page(
        session, select(JobVerdict).where(JobVerdict.job_id == job.id), JobVerdict, limit, cursor
    )
    return [verdict_json(row) for row in rows], next_cursor
