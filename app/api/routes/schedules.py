"""Schedules of a site (cron or interval comparisons), running one now, and their runs."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response

from app.api.deps import PrincipalDep, SessionDep, SettingsDep, WriterDep
from app.services.paging import DEFAULT_LIMIT, MAX_LIMIT
from app.services.schedules import service as schedules_service
from app.services.schedules.schemas import (
    ScheduleCreate,
    ScheduleRead,
    ScheduleRunRead,
    ScheduleUpdate,
)
from app.services.schemas import Page

router = APIRouter(tags=["schedules"])

Limit = Annotated[int, Query(ge=1, le=MAX_LIMIT, description="Items per page.")]
Cursor = Annotated[str | None, Query(description="`next_cursor` of the previous page.")]


@router.post("/sites/{site_id}/schedules", status_code=201, response_model=ScheduleRead)
def create_schedule(
    site_id: str,
    payload: ScheduleCreate,
    session: SessionDep,
    settings: SettingsDep,
    principal: WriterDep,
) -> ScheduleRead:
    """Create a schedule of a site."""
    return schedules_service.create_schedule(session, settings, principal, site_id, payload)


@router.get("/sites/{site_id}/schedules", response_model=list[ScheduleRead])
def list_schedules(
    site_id: str, session: SessionDep, principal: PrincipalDep
) -> list[ScheduleRead]:
    """List a site's schedules."""
    return schedules_service.list_schedules(session, principal, site_id)


@router.get("/schedules/{schedule_id}", response_model=ScheduleRead)
def get_schedule(schedule_id: str, session: SessionDep, principal: PrincipalDep) -> ScheduleRead:
    """Read a schedule."""
    return schedules_service.read_schedule(session, principal, schedule_id)


@router.patch("/schedules/{schedule_id}", response_model=ScheduleRead)
def update_schedule(
    schedule_id: str,
    payload: ScheduleUpdate,
    session: SessionDep,
    settings: SettingsDep,
    principal: WriterDep,
) -> ScheduleRead:
    """Change a schedule."""
    return schedules_service.update_schedule(session, settings, principal, schedule_id, payload)


@router.delete("/schedules/{schedule_id}", status_code=204, response_class=Response)
def delete_schedule(schedule_id: str, session: SessionDep, principal: WriterDep) -> Response:
    """Delete a schedule and its runs."""
    schedules_service.delete_schedule(session, principal, schedule_id)
    return Response(status_code=204)


@router.post("/schedules/{schedule_id}/run", status_code=201, response_model=ScheduleRunRead)
def run_schedule(
    schedule_id: str, session: SessionDep, settings: SettingsDep, principal: WriterDep
) -> ScheduleRunRead:
    """Run a schedule now, outside its rhythm."""
    return schedules_service.run_now(session, settings, principal, schedule_id)


@router.get("/schedules/{schedule_id}/runs", response_model=Page[ScheduleRunRead])
def list_runs(
    schedule_id: str,
    session: SessionDep,
    principal: PrincipalDep,
    limit: Limit = DEFAULT_LIMIT,
    cursor: Cursor = None,
) -> Page[ScheduleRunRead]:
    """A schedule's runs, newest first."""
    rows, next_cursor = schedules_service.list_runs(session, principal, schedule_id, limit, cursor)
    return Page[ScheduleRunRead](
        items=[ScheduleRunRead.from_model(row) for row in rows], next_cursor=next_cursor
    )
