"""Per-organisation quotas: unfinished jobs (429) and stored scan bytes (507), and their usage.

*Queued jobs* are an organisation's jobs that have not finished (``queued`` or ``running``);
*stored bytes* are the sizes of its scan files as uploaded (``scan.size_bytes``) and of the k-NN
geometry cached for the scans compared as references (``scan.geometry_cache_bytes``, written by
the job workers: :mod:`app.jobs.geometry`), plus the bytes already accepted by the unexpired
resumable uploads still receiving (:mod:`app.services.resumable_uploads`).  Result files
(labels, PLY/LAS exports) are not counted: they are derived from the scans, bounded by them and
deleted with them.

The authoritative checks run inside the write transaction that inserts the scan or the job, after
:func:`lock_organisation`: on SQLite that transaction is ``BEGIN IMMEDIATE`` (writers take turns),
on PostgreSQL the organisation row is locked ``FOR UPDATE``, so two concurrent uploads of one
organisation cannot both pass the check with the same usage.  The cap on unfinished jobs is
checked there only, by :func:`app.services.jobs.new_job` (every job is created by it).  The
storage cap is also checked earlier (before a body is read, while and after it streams): those
checks refuse a large upload sooner and never replace the last one.
"""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from app.config import Settings
from app.db import usage
from app.db.models import Job, JobStatus, Organisation
from app.services.auth import Principal
from app.services.errors import InsufficientStorageError, NotFoundError, TooManyRequestsError
from app.services.scoping import scoped

RETRY_AFTER_SECONDS = 30
"""``Retry-After`` of a 429: jobs take seconds to minutes, a fleet should back off that long."""
ORGANISATION_PATH = "/api/v1/organisation"


@dataclass(frozen=True)
class Usage:
    """An organisation (its id and name), its usage and its caps (None = unlimited)."""

    id: str
    name: str
    queued_jobs: int
    max_queued_jobs: int | None
    stored_bytes: int
    max_stored_bytes: int | None


def lock_organisation(session: Session, principal: Principal) -> None:
    """Serialise quota checks of the principal's organisation until the transaction ends
    (:func:`app.db.usage.lock_organisation`, the lock the job workers take too)."""
    usage.lock_organisation(session, principal.organisation_id)


def queued_jobs(session: Session, principal: Principal) -> int:
    """The organisation's jobs that have not finished (queued or running)."""
    unfinished = select(func.count()).select_from(Job).where(Job.status.in_(JobStatus.unfinished()))
    count = session.scalar(scoped(unfinished, principal))
    return int(count or 0)


def stored_bytes(session: Session, principal: Principal) -> int:
    """Bytes of the organisation's scan files, their cached reference geometry and its
    resumable uploads in progress (:func:`app.db.usage.stored_bytes`, the sum the job workers
    count too)."""
    return usage.stored_bytes(session, principal.organisation_id)


def queued_jobs_message(queued: int, cap: int) -> str:
    """The 429 message: how many, the cap, what to do."""
    return (
        f"the organisation has {queued} unfinished jobs (queued or running) and the cap is {cap} "
        f"(SCANDIFF_MAX_QUEUED_JOBS_PER_ORGANISATION): nothing was stored; wait for jobs to "
        f"finish and retry after {RETRY_AFTER_SECONDS} s (GET {ORGANISATION_PATH} shows the "
        f"count)"
    )


def storage_message(used: int, cap: int, adding: int | None, *, at_least: bool = False) -> str:
    """The 507 message: usage, the upload (``at_least`` while it streams), the cap, what to do."""
    if adding is None:
        upload = ""
    else:
        upload = f", this upload adds {'more than ' if at_least else ''}{adding}"
    return (
        f"storage quota exceeded: the organisation stores {used} bytes of scans{upload} and "
        f"the cap is {cap} (SCANDIFF_MAX_STORED_BYTES_PER_ORGANISATION), "
        f"{max(cap - used, 0)} bytes left: nothing was stored; free space by deleting sites "
        f"you no longer need (DELETE /api/v1/sites/{{site_id}} removes their scans and "
        f"results), then retry (GET {ORGANISATION_PATH} shows the usage)"
    )


def check_queued_jobs(
    session: Session, settings: Settings, principal: Principal, adding: int = 1
) -> None:
    """429 when ``adding`` more jobs would pass the organisation's cap on unfinished jobs."""
    cap = settings.max_queued_jobs_per_organisation
    if cap is None:
        return
    queued = queued_jobs(session, principal)
    if queued + adding > cap:
        raise TooManyRequestsError(
            queued_jobs_message(queued, cap),
            retry_after_seconds=RETRY_AFTER_SECONDS,
            code="too_many_queued_jobs",
        )


def storage_error(
    used: int, cap: int, adding: int | None, *, at_least: bool = False
) -> InsufficientStorageError:
    """The 507 for an upload of ``adding`` bytes (None: of unknown size)."""
    return InsufficientStorageError(
        storage_message(used, cap, adding, at_least=at_least), code="storage_quota_exceeded"
    )


def check_stored_bytes(
    session: Session, settings: Settings, principal: Principal, adding: int | None
) -> None:
    """507 when ``adding`` bytes more (None: any upload, at least 1 byte) pass the cap."""
    cap = settings.max_stored_bytes_per_organisation
    if cap is None:
        return
    used = stored_bytes(session, principal)
    if used + (1 if adding is None else adding) > cap:
        raise storage_error(used, cap, adding)


def remaining_bytes(session: Session, settings: Settings, principal: Principal) -> int | None:
    """Bytes the organisation may still store (None = unlimited); a hint, not a reservation."""
    cap = settings.max_stored_bytes_per_organisation
    if cap is None:
        return None
    return max(cap - stored_bytes(session, principal), 0)


def organisation_usage(session: Session, settings: Settings, principal: Principal) -> Usage:
    """The organisation's queued jobs and stored bytes with their caps."""
    organisation = session.get(Organisation, principal.organisation_id)
    if organisation is None:
        raise NotFoundError(f"organisation {principal.organisation_id} not found")
    return Usage(
        id=organisation.id,
        name=organisation.name,
        queued_jobs=queued_jobs(session, principal),
        max_queued_jobs=settings.max_queued_jobs_per_organisation,
        stored_bytes=stored_bytes(session, principal),
        max_stored_bytes=settings.max_stored_bytes_per_organisation,
    )
