"""Review verdicts on jobs: confirmed, false alarm, or the job's scan as the new reference."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query

from app.api.deps import PrincipalDep, SessionDep, SettingsDep, WriterDep
from app.services import verdicts as verdicts_service
from app.services.paging import DEFAULT_LIMIT, MAX_LIMIT
from app.services.schemas import ErrorRead, JobRead, Page, VerdictCreate, VerdictRead

router = APIRouter(tags=["jobs"])


@router.post(
    "/jobs/{job_id}/verdict",
    response_model=JobRead,
    responses={409: {"model": ErrorRead, "description": "The job has not succeeded."}},
)
def set_verdict(
    job_id: str,
    payload: VerdictCreate,
    session: SessionDep,
    settings: SettingsDep,
    principal: WriterDep,
) -> JobRead:
    """Give a succeeded job a review verdict (replaces the current one; history is kept)."""
    return JobRead.from_model(
        verdicts_service.set_verdict(session, settings, principal, job_id, payload)
    )


@router.get("/jobs/{job_id}/verdicts", response_model=Page[VerdictRead])
def list_verdicts(
    job_id: str,
    session: SessionDep,
    principal: PrincipalDep,
    limit: Annotated[int, Query(ge=1, le=MAX_LIMIT, description="Items per page.")] = DEFAULT_LIMIT,
    cursor: Annotated[str | None, Query(description="`next_cursor` of the previous page.")] = None,
) -> Page[VerdictRead]:
    """Every verdict given to the job, newest first (the first is the current one)."""
    entries, next_cursor = verdicts_service.list_verdicts(session, principal, job_id, limit, cursor)
    return Page[VerdictRead](
        items=[VerdictRead.model_validate(entry) for entry in entries], next_cursor=next_cursor
    )
