"""Comparison jobs: creation, state and results."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Literal

from fastapi import APIRouter, Header, Query, Response
from fastapi.responses import FileResponse, JSONResponse
from starlette.concurrency import run_in_threadpool

from app.api.deps import PrincipalDep, SessionDep, SettingsDep, WriterDep
from app.api.errors import QUEUED_JOBS_RESPONSE
from app.db.models import JobStatus
from app.services import jobs as jobs_service
from app.services import results as results_service
from app.services.paging import DEFAULT_LIMIT, MAX_LIMIT
from app.services.schemas import (
    AwaitingReviewCounts,
    ErrorRead,
    JobCreate,
    JobRead,
    JobRerun,
    Page,
    RegionRead,
    SiteAwaitingReview,
)

router = APIRouter(tags=["jobs"])

Limit = Annotated[int, Query(ge=1, le=MAX_LIMIT, description="Items per page.")]
Cursor = Annotated[str | None, Query(description="`next_cursor` of the previous page.")]
REGION_PAGE_MAX = 1000
"""Largest page of ``GET /jobs/{id}/regions`` (regions are small; a job can have thousands)."""

REGION_TOTAL_HEADER = {
    "description": "How many regions match the filters (all pages).",
    "schema": {"type": "integer"},
}


@router.post(
    "/jobs", status_code=202, response_model=JobRead, responses={429: QUEUED_JOBS_RESPONSE}
)
def create_job(
    payload: JobCreate,
    session: SessionDep,
    settings: SettingsDep,
    principal: WriterDep,
    idempotency_key: Annotated[str | None, Header(alias="Idempotency-Key")] = None,
) -> JSONResponse:
    """Queue a comparison of two scans of one site (e.g. a re-run with other parameters)."""
    stored = jobs_service.create_job(session, settings, principal, payload, idempotency_key)
    return JSONResponse(stored.body, status_code=stored.status_code)


@router.get("/jobs", response_model=Page[JobRead])
def list_jobs(
    session: SessionDep,
    principal: PrincipalDep,
    site_id: Annotated[str | None, Query(description="Only this site's jobs.")] = None,
    status: Annotated[JobStatus | None, Query(description="Only jobs in this state.")] = None,
    changed: Annotated[bool | None, Query(description="Only jobs with this decision.")] = None,
    verdict: Annotated[
        Literal["confirmed", "false_alarm", "new_reference", "none"] | None,
        Query(description="Only jobs with this current verdict; none: awaiting a verdict."),
    ] = None,
    created_after: Annotated[
        datetime | None, Query(description="Only jobs created at or after this time.")
    ] = None,
    created_before: Annotated[
        datetime | None, Query(description="Only jobs created before this time.")
    ] = None,
    limit: Limit = DEFAULT_LIMIT,
    cursor: Cursor = None,
) -> Page[JobRead]:
    """The organisation's jobs, newest first, filtered by site, status, decision and verdict."""
    rows, next_cursor = jobs_service.list_jobs(
        session,
        principal,
        site_id=site_id,
        status=status,
        changed=changed,
        verdict=verdict,
        created_after=created_after,
        created_before=created_before,
        limit=limit,
        cursor=cursor,
    )
    return Page[JobRead](items=[JobRead.from_model(row) for row in rows], next_cursor=next_cursor)


@router.get("/jobs/awaiting-review/counts", response_model=AwaitingReviewCounts)
def awaiting_review_counts(session: SessionDep, principal: PrincipalDep) -> AwaitingReviewCounts:
    """How many succeeded jobs await a verdict, in all and per site (the review inbox)."""
    sites = [
        SiteAwaitingReview(**entry)
        for entry in jobs_service.awaiting_review_counts(session, principal)
    ]
    return AwaitingReviewCounts(total=sum(site.count for site in sites), sites=sites)


@router.get("/jobs/{job_id}", response_model=JobRead)
async def get_job(
    job_id: str,
    session: SessionDep,
    settings: SettingsDep,
    principal: PrincipalDep,
    wait: Annotated[
        float,
        Query(
            ge=0,
            le=jobs_service.JOB_WAIT_MAX_SECONDS,
            description=(
                "Long poll: when the job has not ended (succeeded or failed), hold the answer "
                "until it ends or this many seconds pass, then return the job as it is then."
            ),
        ),
    ] = 0.0,
) -> JobRead:
    """Read a job's state and results; with ``wait``, once it ended or the wait is over."""

    def read() -> tuple[JobRead, bool]:
        job = jobs_service.get_job(session, principal, job_id)
        answer, ended = JobRead.from_model(job), job.status in jobs_service.JOB_ENDED
        if wait > 0 and not ended:
            session.rollback()  # end the read transaction: the wait and re-read see new commits
        return answer, ended

    # the most polled endpoint: one thread hop for the query (an async route's response is
    # also validated on the event loop, where a sync route would need a second hop)
    job, ended = await run_in_threadpool(read)
    if wait <= 0 or ended:
        return job
    await jobs_service.wait_for_job_end(settings, job.id, wait)
    return await run_in_threadpool(
        lambda: JobRead.from_model(jobs_service.get_job(session, principal, job_id))
    )


@router.post(
    "/jobs/{job_id}/rerun",
    status_code=202,
    response_model=JobRead,
    responses={429: QUEUED_JOBS_RESPONSE},
)
def rerun_job(
    job_id: str,
    session: SessionDep,
    settings: SettingsDep,
    principal: WriterDep,
    payload: JobRerun | None = None,
    idempotency_key: Annotated[str | None, Header(alias="Idempotency-Key")] = None,
) -> JSONResponse:
    """Queue a new job on this job's reference and scan, with another detector or parameters."""
    stored = jobs_service.rerun_job(
        session, settings, principal, job_id, payload or JobRerun(), idempotency_key
    )
    return JSONResponse(stored.body, status_code=stored.status_code)


@router.get(
    "/jobs/{job_id}/regions",
    response_model=Page[RegionRead],
    responses={200: {"headers": {"X-Total-Count": REGION_TOTAL_HEADER}}},
)
def list_regions(
    job_id: str,
    response: Response,
    session: SessionDep,
    principal: PrincipalDep,
    kind: Annotated[
        Literal["added", "removed"] | None, Query(description="Only regions of this kind.")
    ] = None,
    min_points: Annotated[
        int | None, Query(ge=0, description="Only regions of at least this many points.")
    ] = None,
    sort: Annotated[
        str,
        Query(
            description="ordinal (the job's order), kind, n_points, mean_distance or max_distance."
        ),
    ] = "ordinal",
    order: Annotated[Literal["asc", "desc"], Query(description="Sort direction.")] = "asc",
    limit: Annotated[
        int, Query(ge=1, le=REGION_PAGE_MAX, description="Regions per page.")
    ] = DEFAULT_LIMIT,
    cursor: Cursor = None,
) -> Page[RegionRead]:
    """The changed regions the job found (empty until it succeeded); X-Total-Count: matches."""
    regions, next_cursor, total = jobs_service.list_regions(
        session,
        principal,
        job_id,
        kind=kind,
        min_points=min_points,
        sort=sort,
        descending=order == "desc",
        limit=limit,
        cursor=cursor,
    )
    response.headers["X-Total-Count"] = str(total)
    return Page[RegionRead](
        items=[RegionRead.from_model(region) for region in regions], next_cursor=next_cursor
    )


@router.get(
    "/jobs/{job_id}/labels",
    response_class=FileResponse,
    responses={409: {"model": ErrorRead, "description": "The job has not succeeded."}},
)
def get_labels(
    job_id: str,
    session: SessionDep,
    settings: SettingsDep,
    principal: PrincipalDep,
    format: Annotated[Literal["npz", "ply", "las"], Query(description="File format.")] = "npz",
) -> FileResponse:
    """Per-point labels: the npz of `scandiff compare --labels`, or both clouds as PLY/LAS."""
    download = results_service.labels_file(session, settings, principal, job_id, format)
    return FileResponse(download.path, media_type=download.media_type, filename=download.filename)
