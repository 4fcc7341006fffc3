"""Schedules of a site: create, read, change, delete, run now, and the runs' history.

A schedule fires on a cron expression in an IANA time zone or on a fixed interval
(:mod:`app.services.schedules.times`); each period is run once by the tick of the job consumers
(:mod:`app.services.schedules.runs`), which compares the newest scan that arrived since the last
run against the site's reference (and against the previous scan with ``compare_previous``).
Where scans come from is the schedule's source (:mod:`app.services.schedules.sources`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from app.clock import as_utc, utc_now
from app.config import Settings
from app.db.models import Schedule, ScheduleRun, Site
from app.services import sites
from app.services.auth import Principal
from app.services.errors import NotFoundError, ValidationFailedError
from app.services.paging import newest_first_page
from app.services.schedules import runs as schedule_runs
from app.services.schedules.schemas import (
    ScheduleCreate,
    ScheduleRead,
    ScheduleRunRead,
    ScheduleUpdate,
)
from app.services.schedules.sources import normalise_source
from app.services.schedules.times import check_cron, parse_timezone
from app.services.schemas import DetectorConfig
from app.services.scoping import scoped
from app.services.transaction import end_read_transaction


def check_rhythm(settings: Settings, cron: str | None, interval_seconds: int | None) -> None:
    """Exactly one of a valid cron expression and a long enough interval; 422 otherwise."""
    if (cron is None) == (interval_seconds is None):
        raise ValidationFailedError(
            "give exactly one of cron (e.g. '0 2 * * *') and interval_seconds, not "
            f"{'both' if cron is not None else 'neither'}",
            code="invalid_rhythm",
        )
    if cron is not None:
        check_cron(cron)
    if interval_seconds is not None and interval_seconds < settings.schedule_min_interval_seconds:
        raise ValidationFailedError(
            f"interval_seconds must be at least {settings.schedule_min_interval_seconds} "
            f"(SCANDIFF_SCHEDULE_MIN_INTERVAL_SECONDS), got {interval_seconds}",
            code="invalid_rhythm",
        )


def _detector_json(site: Site, detector: DetectorConfig | None) -> dict[str, Any] | None:
    if detector is None:
        return None
    sites.resolve_detector(site, detector.method, detector.variant, dict(detector.params))
    return detector.model_dump(mode="json")


def public_source(source: dict[str, Any]) -> Any:
    """A stored source as the API shows it (the form it was given in)."""
    if source.get("kind") == "directory":
        return {"directory": source["directory"]}
    if source.get("kind") == "url":
        return {"url": source["url"]}
    return "uploads"


def schedule_read(schedule: Schedule) -> ScheduleRead:
    """The API view of a schedule, with its next fire time."""
    rhythm = schedule_runs.rhythm_of(schedule)
    after = max(as_utc(schedule.last_period_start or schedule.created_at), utc_now())
    return ScheduleRead(
        id=schedule.id,
        site_id=schedule.site_id,
        cron=schedule.cron,
        interval_seconds=schedule.interval_seconds,
        timezone=schedule.timezone,
        source=public_source(schedule.source),
        stale_after_seconds=schedule.stale_after_seconds,
        detector=DetectorConfig(**schedule.detector) if schedule.detector else None,
        catch_up=schedule.catch_up,  # type: ignore[arg-type]
        compare_previous=schedule.compare_previous,
        enabled=schedule.enabled,
        last_period_start=schedule.last_period_start,
        next_run_at=rhythm.next_after(after) if schedule.enabled else None,
        stale_since=schedule.stale_since,
        missed_since=schedule.missed_since,
        created_at=schedule.created_at,
    )


def get_schedule(session: Session, principal: Principal, schedule_id: str) -> Schedule:
    """The principal's schedule ``schedule_id``; 404 when it does not exist or is another's."""
    schedule = session.scalar(scoped(select(Schedule).where(Schedule.id == schedule_id), principal))
    if schedule is None:
        raise NotFoundError(f"schedule {schedule_id} not found")
    return schedule


def create_schedule(
    session: Session,
    settings: Settings,
    principal: Principal,
    site_id: str,
    payload: ScheduleCreate,
) -> ScheduleRead:
    """Create a schedule of a site (rhythm, zone, source and detector checked)."""
    site = sites.get_site(session, principal, site_id)
    check_rhythm(settings, payload.cron, payload.interval_seconds)
    parse_timezone(payload.timezone)
    source = payload.source.model_dump() if hasattr(payload.source, "model_dump") else None
    schedule = Schedule(
        organisation_id=principal.organisation_id,
        site_id=site.id,
        cron=payload.cron,
        interval_seconds=payload.interval_seconds,
        timezone=payload.timezone,
        source=normalise_source(settings, source or payload.source),
        stale_after_seconds=payload.stale_after_seconds,
        detector=_detector_json(site, payload.detector),
        catch_up=payload.catch_up,
        compare_previous=payload.compare_previous,
        enabled=payload.enabled,
        created_at=utc_now(),
    )
    session.add(schedule)
    session.flush()
    return schedule_read(schedule)


def list_schedules(session: Session, principal: Principal, site_id: str) -> list[ScheduleRead]:
    """A site's schedules, oldest first."""
    site = sites.get_site(session, principal, site_id)
    rows = session.scalars(
        scoped(select(Schedule).where(Schedule.site_id == site.id), principal).order_by(
            Schedule.created_at, Schedule.id
        )
    ).all()
    return [schedule_read(row) for row in rows]


def read_schedule(session: Session, principal: Principal, schedule_id: str) -> ScheduleRead:
    """One schedule."""
    return schedule_read(get_schedule(session, principal, schedule_id))


def update_schedule(
    session: Session,
    settings: Settings,
    principal: Principal,
    schedule_id: str,
    payload: ScheduleUpdate,
) -> ScheduleRead:
    """Change the fields given; the result is checked as a whole (422 saying what to fix)."""
    schedule = get_schedule(session, principal, schedule_id)
    fields = payload.model_fields_set
    if payload.enabled and not schedule.enabled:
        schedule.last_period_start = utc_now()  # re-enabled: no catch-up of the paused periods
    for name in ("timezone", "catch_up", "compare_previous", "enabled"):
        if name in fields:
            value = getattr(payload, name)
            if value is None:
                raise ValidationFailedError(f"{name} cannot be null")
            setattr(schedule, name, value)
    if "cron" in fields:
        schedule.cron = payload.cron
    if "interval_seconds" in fields:
        schedule.interval_seconds = payload.interval_seconds
    if "stale_after_seconds" in fields:
        schedule.stale_after_seconds = payload.stale_after_seconds
    if "source" in fields:
        source = payload.source
        raw = source.model_dump() if hasattr(source, "model_dump") else source
        schedule.source = normalise_source(settings, raw)
        schedule.source_marker = None
    if "detector" in fields:
        site = sites.get_site(session, principal, schedule.site_id)
        schedule.detector = _detector_json(site, payload.detector)
    check_rhythm(settings, schedule.cron, schedule.interval_seconds)
    parse_timezone(schedule.timezone)
    session.flush()
    return schedule_read(schedule)


def delete_schedule(session: Session, principal: Principal, schedule_id: str) -> None:
    """Delete a schedule and its runs (the scans and jobs they made stay)."""
    schedule = get_schedule(session, principal, schedule_id)
    session.execute(delete(ScheduleRun).where(ScheduleRun.schedule_id == schedule.id))
    session.delete(schedule)
    session.flush()


def list_runs(
    session: Session, principal: Principal, schedule_id: str, limit: int, cursor: str | None
) -> tuple[Sequence[ScheduleRun], str | None]:
    """A schedule's runs, newest first, one page."""
    schedule = get_schedule(session, principal, schedule_id)
    statement = scoped(select(ScheduleRun).where(ScheduleRun.schedule_id == schedule.id), principal)
    return newest_first_page(session, statement, ScheduleRun, limit, cursor)


def run_now(
    session: Session, settings: Settings, principal: Principal, schedule_id: str
) -> ScheduleRunRead:
    """Run a schedule's period now (a manual run); its source's refusals are 4xx."""
    owned_id = get_schedule(session, principal, schedule_id).id
    end_read_transaction(session)  # the run has its own transactions; a fetch holds no lock
    run = schedule_runs.run_manual(settings, owned_id)
    return ScheduleRunRead.from_model(run)
