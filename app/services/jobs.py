"""Comparison jobs: creation (enqueued after commit), reads, the site timeline and regions.

The job row is the truth; the queue only carries its id.  Every job is created by
:func:`new_job`, which checks the organisation's cap on unfinished jobs (429) under the
organisation lock of :mod:`app.services.quotas`, in the transaction that inserts the job: the
one check of that cap, for an upload as for ``POST /jobs``.  A job is enqueued only after the
transaction that created it committed (an enqueue that fails leaves the job ``queued`` for the
recovery sweep).  Running jobs is the worker's business (:mod:`app.jobs`).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from datetime import datetime
from typing import Any

import anyio
from sqlalchemy import func, select
from sqlalchemy.orm import Session, selectinload

from app.clock import as_utc
from app.config import Settings
from app.db.models import IdempotencyRecord, Job, JobStatus, Region, Scan, Site
from app.db.session import session_factory
from app.jobs.queue import enqueue_job
from app.log import current_request_id
from app.services import idempotency, quotas, sites
from app.services.auth import Principal
from app.services.errors import ValidationFailedError
from app.services.idempotency import StoredResponse
from app.services.paging import DEFAULT_LIMIT, newest_first_page, offset_page
from app.services.schemas import JobCreate, JobRead, JobRerun
from app.services.scoping import get_owned, scoped
from app.services.transaction import after_commit


def new_job(
    session: Session,
    settings: Settings,
    principal: Principal,
    *,
    site_id: str,
    reference_scan_id: str,
    scan_id: str,
    method: str,
    variant: str,
    params: dict[str, Any],
) -> Job:
    """Insert a queued job (429 at the organisation's cap) and enqueue it after commit.

    The job keeps the id of the API request creating it (``request_id``; None outside one).
    """
    quotas.lock_organisation(session, principal)
    quotas.check_queued_jobs(session, settings, principal)
    job = Job(
        organisation_id=principal.organisation_id,
        site_id=site_id,
        reference_scan_id=reference_scan_id,
        scan_id=scan_id,
        method=method,
        variant=variant,
        params=params,
        status=JobStatus.QUEUED,
        progress=0.0,
        attempts=0,
        max_attempts=settings.job_max_attempts,
        request_id=current_request_id(),  # the creating request's id, for the worker's logs
    )
    session.add(job)
    session.flush()
    job_id = job.id
    after_commit(session, lambda: enqueue_job(job_id, settings))
    return job


def create_job(
    session: Session,
    settings: Settings,
    principal: Principal,
    payload: JobCreate,
    idempotency_key: str | None,
) -> StoredResponse:
    """Create a comparison of two scans of one site (202), replaying on a known key."""
    record, stored = idempotency.claim_request(
        session, principal, idempotency_key, "/api/v1/jobs", payload.model_dump(mode="json")
    )
    if stored is not None:
        return stored
    reference = get_owned(session, principal, Scan, payload.reference_scan_id)
    scan = get_owned(session, principal, Scan, payload.scan_id)
    if reference.site_id != scan.site_id:
        raise ValidationFailedError(
            "the reference and the scan belong to different sites; compare scans of one site",
            code="scans_of_different_sites",
        )
    check_memory_budget(settings, reference, scan)
    check_disk_space(settings, reference, scan)
    site = sites.get_site(session, principal, scan.site_id)
    method, variant, params = sites.resolve_detector(
        site, payload.method, payload.variant, payload.params
    )
    return _queue_and_remember(
        session,
        settings,
        principal,
        record,
        site_id=site.id,
        reference_scan_id=reference.id,
        scan_id=scan.id,
        method=method,
        variant=variant,
        params=params,
    )


def check_memory_budget(settings: Settings, reference: Scan, scan: Scan) -> None:
    """422 when the workers' memory budget cannot hold what comparing ``reference`` and
    ``scan`` keeps whole and one tile of it: both clouds, or for a pair a worker reads in
    chunks (:func:`app.jobs.execution.streamed_tiles`) each cloud's subsample only."""
    from app.core.tiling.plan import (
        BASELINE_BYTES,
        LEAN_RESIDENT_BYTES_PER_POINT,
        RESIDENT_BYTES_PER_POINT,
        crop_point_limit,
    )

    budget = settings.worker_memory_budget_bytes
    n_points = reference.n_points + scan.n_points
    if budget is None or crop_point_limit(budget, n_points) > 0:
        return
    needed = BASELINE_BYTES + n_points * RESIDENT_BYTES_PER_POINT
    if all(_read_in_chunks(settings, row) for row in (reference, scan)):
        from app.core.tiling.streamed import SUBSAMPLE_POINTS  # big pairs only: a heavy import

        kept = sum(min(row.n_points, SUBSAMPLE_POINTS) for row in (reference, scan))
        if crop_point_limit(budget, kept, LEAN_RESIDENT_BYTES_PER_POINT) > 0:
            return
        needed = BASELINE_BYTES + kept * LEAN_RESIDENT_BYTES_PER_POINT
    raise ValidationFailedError(
        f"the two scans' {n_points:,} points do not fit the workers' memory budget "
        f"({budget / 1024**2:,.0f} MiB, SCANDIFF_WORKER_MEMORY_BUDGET_BYTES): holding them "
        f"alone needs about {needed / 1024**2:,.0f} MiB before any tile is compared; ask the "
        "operator to raise it, or compare smaller scans",
        code="memory_budget_too_small",
    )


def check_disk_space(settings: Settings, reference: Scan, scan: Scan) -> None:
    """422 when a pair the workers compare in tiles cannot fit the data directory's free disk:
    each of its points is in at least one tile's crop and has a result
    (:data:`~app.core.tiling.disk.MIN_BYTES_PER_POINT`), beside what must stay free."""
    from app.core.tiling.disk import MIN_BYTES_PER_POINT, free_disk_bytes
    from app.core.tiling.plan import crop_point_limit

    n_points = reference.n_points + scan.n_points
    budget = settings.worker_memory_budget_bytes
    tiled = bool(settings.tile_crop_points) or (
        budget is not None and crop_point_limit(budget, n_points) < n_points
    )
    if not tiled:
        return
    needed = n_points * MIN_BYTES_PER_POINT
    free = free_disk_bytes(settings.data_dir)
    if needed + settings.min_free_disk_bytes <= free:
        return
    raise ValidationFailedError(
        f"not enough disk to compare these scans: their {n_points:,} points are compared in "
        f"tiles whose inputs and results need at least {needed / 1e9:,.1f} GB under the data "
        f"directory, which has {free / 1e9:,.1f} GB free and must keep "
        f"{settings.min_free_disk_bytes / 1e9:,.1f} GB free (SCANDIFF_MIN_FREE_DISK_BYTES); "
        "ask the operator to free disk, or compare smaller scans",
        code="insufficient_disk",
    )


def _read_in_chunks(settings: Settings, row: Scan) -> bool:
    """Whether a worker reads this stored scan in chunks when its pair is tiled: a binary PLY
    or ``.npy`` of coordinates only, no origin stored, no trajectory or bag options beside it
    (the per-file half of :func:`app.jobs.execution.streamed_tiles`)."""
    from app.core.tiling.pair_files import coordinates_only
    from app.kit.data_layout import StoredPathError
    from app.kit.scan_files import bag_options_path, trajectory_path

    if row.sensor_origin is not None:
        return False
    try:
        path = settings.data_layout.resolve(row.storage_path)
    except StoredPathError:
        return False
    beside = trajectory_path(path).exists() or bag_options_path(path).exists()
    return not beside and coordinates_only(path, row.format)


def rerun_job(
    session: Session,
    settings: Settings,
    principal: Principal,
    job_id: str,
    payload: JobRerun,
    idempotency_key: str | None,
) -> StoredResponse:
    """Queue a new job on a job's reference and scan, with another detector or parameters."""
    record, stored = idempotency.claim_request(
        session,
        principal,
        idempotency_key,
        f"/api/v1/jobs/{job_id}/rerun",
        payload.model_dump(mode="json"),
    )
    if stored is not None:
        return stored
    original = get_job(session, principal, job_id)
    method = payload.method or original.method
    variant = payload.variant or original.variant
    params = payload.params
    if params is None:
        same_detector = (method, variant) == (original.method, original.variant)
        params = dict(original.params or {}) if same_detector else {}
    sites.validate_detector(method, variant, params)
    return _queue_and_remember(
        session,
        settings,
        principal,
        record,
        site_id=original.site_id,
        reference_scan_id=original.reference_scan_id,
        scan_id=original.scan_id,
        method=method,
        variant=variant,
        params=params,
    )


def _queue_and_remember(
    session: Session,
    settings: Settings,
    principal: Principal,
    record: IdempotencyRecord | None,
    **job_fields: Any,
) -> StoredResponse:
    """Queue a new job and remember the 202 answer under the request's idempotency record."""
    job = new_job(session, settings, principal, **job_fields)
    response = StoredResponse(202, JobRead.from_model(job).model_dump(mode="json"))
    return idempotency.remember(record, response)


def get_job(session: Session, principal: Principal, job_id: str) -> Job:
    """The principal's job ``job_id``; 404 when it does not exist or is another's."""
    return get_owned(session, principal, Job, job_id)


JOB_ENDED = frozenset({JobStatus.SUCCEEDED, JobStatus.FAILED})
"""Statuses a job never leaves."""
JOB_WAIT_MAX_SECONDS = 10.0
"""Longest wait ``GET /jobs/{id}?wait=`` may ask for (clients ask again)."""
JOB_WAIT_CHECK_SECONDS = 0.05
"""How often a waiting request reads the job's status (one indexed column, no HTTP round trip)."""


def job_has_ended(settings: Settings, job_id: str) -> bool:
    """Whether job ``job_id`` succeeded or failed (or no longer exists), from one short read."""
    session = session_factory(settings.sqlalchemy_url, read_only=True)()
    try:
        status = session.scalar(select(Job.status).where(Job.id == job_id))
    finally:
        session.close()
    return status is None or status in JOB_ENDED


async def wait_for_job_end(settings: Settings, job_id: str, seconds: float) -> bool:
    """Wait until job ``job_id`` has ended or ``seconds`` passed; whether it ended.

    The long poll of ``GET /jobs/{id}?wait=``: the status is read every
    :data:`JOB_WAIT_CHECK_SECONDS` in a worker thread, the request sleeping on the event loop
    in between, so a waiting client costs a small read a check instead of a whole request.
    """
    deadline = time.monotonic() + min(max(seconds, 0.0), JOB_WAIT_MAX_SECONDS)
    while True:
        if await anyio.to_thread.run_sync(job_has_ended, settings, job_id):
            return True
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return False
        await anyio.sleep(min(JOB_WAIT_CHECK_SECONDS, remaining))


def list_site_jobs(
    session: Session,
    principal: Principal,
    site_id: str,
    *,
    changed: bool | None,
    status: JobStatus | None,
    since: datetime | None,
    limit: int,
    cursor: str | None,
) -> tuple[Sequence[Job], str | None]:
    """A site's jobs, newest first, filtered by decision, status and creation time; one page."""
    site = sites.get_site(session, principal, site_id)
    statement = scoped(select(Job).where(Job.site_id == site.id), principal)
    if changed is not None:
        statement = statement.where(Job.changed.is_(changed))
    if status is not None:
        statement = statement.where(Job.status == status)
    if since is not None:
        statement = statement.where(Job.created_at >= as_utc(since))
    # the scans' file names of the whole page in two queries, not two per job
    statement = statement.options(selectinload(Job.reference_scan), selectinload(Job.scan))
    return newest_first_page(session, statement, Job, limit, cursor)


VERDICT_FILTERS = ("confirmed", "false_alarm", "new_reference", "none")
"""What ``GET /jobs?verdict=`` accepts: a current verdict, or ``none`` (awaiting a verdict)."""


def _verdict_of_job() -> Any:
    """The SQL expression of a job's current verdict name (NULL without one), on any database."""
    return Job.verdict["verdict"].as_string()


def list_jobs(
    session: Session,
    principal: Principal,
    *,
    site_id: str | None = None,
    status: JobStatus | None = None,
    changed: bool | None = None,
    verdict: str | None = None,
    created_after: datetime | None = None,
    created_before: datetime | None = None,
    limit: int = DEFAULT_LIMIT,
    cursor: str | None = None,
) -> tuple[Sequence[Job], str | None]:
    """The organisation's jobs, newest first, filtered by site, status, decision, verdict and
    creation time (``created_after`` <= created_at < ``created_before``); one page."""
    statement = scoped(select(Job), principal)
    if site_id is not None:
        statement = statement.where(Job.site_id == sites.get_site(session, principal, site_id).id)
    if status is not None:
        statement = statement.where(Job.status == status)
    if changed is not None:
        statement = statement.where(Job.changed.is_(changed))
    if verdict == "none":
        statement = statement.where(_verdict_of_job().is_(None))
    elif verdict is not None:
        statement = statement.where(_verdict_of_job() == verdict)
    if created_after is not None:
        statement = statement.where(Job.created_at >= as_utc(created_after))
    if created_before is not None:
        statement = statement.where(Job.created_at < as_utc(created_before))
    statement = statement.options(selectinload(Job.reference_scan), selectinload(Job.scan))
    return newest_first_page(session, statement, Job, limit, cursor)


def awaiting_review_counts(session: Session, principal: Principal) -> list[dict[str, Any]]:
    """Per site with succeeded jobs awaiting a verdict: its id, name, how many, the newest one's
    creation time; the sites with the newest waiting job first."""
    newest = func.max(Job.created_at)
    statement = scoped(
        select(Job.site_id, func.count(Job.id), newest)
        .where(Job.status == JobStatus.SUCCEEDED, _verdict_of_job().is_(None))
        .group_by(Job.site_id)
        .order_by(newest.desc(), Job.site_id),
        principal,
    )
    counted = session.execute(statement).all()
    names = dict(
        session.execute(
            scoped(select(Site.id, Site.name), principal).where(
                Site.id.in_([site_id for site_id, _, _ in counted])
            )
        ).all()
    )
    return [
        {"site_id": site_id, "site_name": names.get(site_id), "count": int(count),
         "newest_at": as_utc(newest_at)}
        for site_id, count, newest_at in counted
    ]  # fmt: skip


REGION_SORT_KEYS = {
    "ordinal": Region.ordinal,
    "kind": Region.kind,
    "n_points": Region.n_points,
    "mean_distance": Region.mean_distance,
    "max_distance": Region.max_distance,
}
"""What ``GET /jobs/{id}/regions?sort=`` accepts, and the columns they order by."""


def list_regions(
    session: Session,
    principal: Principal,
    job_id: str,
    *,
    kind: str | None = None,
    min_points: int | None = None,
    sort: str = "ordinal",
    descending: bool = False,
    limit: int = DEFAULT_LIMIT,
    cursor: str | None = None,
) -> tuple[Sequence[Region], str | None, int]:
    """A job's regions, filtered, sorted, one page (empty until it succeeded); the next cursor
    and how many match. Ties keep the job's order."""
    if sort not in REGION_SORT_KEYS:
        raise ValidationFailedError(
            f"cannot sort regions by {sort!r}; sort by one of {', '.join(REGION_SORT_KEYS)}",
            code="invalid_sort",
        )
    job = get_job(session, principal, job_id)
    statement = select(Region).where(Region.job_id == job.id)
    if kind:
        statement = statement.where(Region.kind == kind)
    if min_points is not None:
        statement = statement.where(Region.n_points >= min_points)
    total = session.scalar(select(func.count()).select_from(statement.subquery())) or 0
    column = REGION_SORT_KEYS[sort]
    statement = statement.order_by(column.desc() if descending else column.asc(), Region.ordinal)
    rows, next_cursor = offset_page(session, statement, limit, cursor)
    return rows, next_cursor, int(total)
