"""Review verdicts on jobs: confirmed, false alarm, or the job's scan as the new reference."""

from __future__ import annotations

from fastapi import APIRouter

from app.api.deps import PrincipalDep, SessionDep, SettingsDep, WriterDep
from app.services import verdicts as verdicts_service
from app.services.schemas import ErrorRead, JobRead, VerdictCreate, VerdictRead

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


@router.get("/jobs/{job_id}/verdicts", response_model=list[VerdictRead])
def list_verdicts(job_id: str, session: SessionDep, principal: PrincipalDep) -> list[VerdictRead]:
    """Every verdict given to the job, oldest first."""
    return [
        VerdictRead.model_validate(verdict)
        for verdict in verdicts_service.list_verdicts(session, principal, job_id)
    ]
