"""Running schedules: the tick, each period once, catch-up after downtime, missed and stale.

:func:`tick` is called by every job consumer every ``schedule_tick_seconds`` (and by tests with
the ``now`` they choose).  For each enabled schedule it lists the periods that started since
the last one handled (:class:`app.services.schedules.times.Rhythm`) and applies the schedule's
``catch_up`` policy when there are several (the scheduler was down):

* ``each``: every due period runs, oldest first;
* ``latest``: only the newest runs, the older ones are recorded ``skipped``;
* ``none``: periods that started more than :data:`ON_TIME_SECONDS` ago are recorded
  ``skipped``; only a period ticked on time runs.

A period runs at most once, whoever ticks (two consumers, an API's "run now", a restart midway):
its run row is inserted first, in its own committed transaction, and the unique
``(schedule_id, period_start)`` makes every other claimant's insert fail, so it leaves.  The
run then takes its scan (the newest that arrived since the last run, or a file its directory or
URL source yields, stored as an upload would be), compares it with the site's reference through
:func:`app.services.jobs.new_job` with the schedule's detector (an existing job of the same pair
is reused only when its method, variant and parameters are the same), and with the previous
scan too when ``compare_previous`` is set.  A manual run ("run now") of an ``uploads`` schedule
compares the site's newest scan at once, even one that arrived before the schedule.  A period
without a scan to compare is ``missed``, with a ``reason`` saying why; ``schedule.missed`` is
published once per missed spell (until a run compares), and a site with no scan for
``stale_after_seconds`` publishes ``site.stale`` once per stale spell (until a scan arrives).
Both events, like the job events, name the site (``site: {id, name}``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import func, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app.clock import as_utc, iso_utc, utc_now
from app.config import Settings
from app.db.events import publish_event
from app.db.models import Job, Scan, Schedule, ScheduleRun, ScheduleRunStatus, Site
from app.db.session import transaction
from app.services import jobs, sites, storage
from app.services.auth import Principal
from app.services.errors import AppError, ConflictError, NotFoundError
from app.services.schedules import ingest as schedule_ingest
from app.services.schedules import sources as schedule_sources
from app.services.schedules.times import Rhythm
from app.services.storage import ReceivedFile

logger = logging.getLogger("scandiff.schedules")

MAX_PERIODS_PER_TICK = 1000
"""The most periods of one schedule one tick handles (older ones are neither run nor
recorded: a one-minute schedule down for a year does not write half a million rows)."""
ON_TIME_SECONDS = 300.0
"""A period ticked within this many seconds of its start is on time (``catch_up: none``)."""


@dataclass
class TickReport:
    """What one tick did: run ids per status, periods skipped, stale events published."""

    runs: dict[str, list[str]] = field(default_factory=dict)
    skipped: int = 0
    stale: int = 0

    def add(self, status: ScheduleRunStatus | str, run_id: str) -> None:
        """Count run ``run_id`` under ``status``."""
        self.runs.setdefault(str(status), []).append(run_id)


def rhythm_of(schedule: Schedule) -> Rhythm:
    """When ``schedule`` fires."""
    return Rhythm(
        cron=schedule.cron,
        interval_seconds=schedule.interval_seconds,
        timezone=schedule.timezone,
        anchor=as_utc(schedule.created_at),
    )


def schedule_principal(schedule: Schedule) -> Principal:
    """The schedule acting for its organisation (a writer) when it creates scans and jobs."""
    return Principal(
        organisation_id=schedule.organisation_id, role="writer", token_id=f"schedule:{schedule.id}"
    )


def claim_period(
    settings: Settings,
    schedule_id: str,
    period_start: datetime,
    kind: str,
    status: ScheduleRunStatus,
) -> str | None:
    """Insert and commit the run row of a period; None when another claimant has it."""
    try:
        with transaction(settings.sqlalchemy_url) as session:
            schedule = session.get(Schedule, schedule_id)
            if schedule is None:
                return None
            run = ScheduleRun(
                organisation_id=schedule.organisation_id,
                schedule_id=schedule.id,
                period_start=as_utc(period_start),
                kind=kind,
                status=status,
                created_at=utc_now(),
                finished_at=utc_now() if status == ScheduleRunStatus.SKIPPED else None,
            )
            session.add(run)
            session.flush()
            if kind == "scheduled":
                last = schedule.last_period_start
                if last is None or as_utc(last) < as_utc(period_start):
                    schedule.last_period_start = as_utc(period_start)
            return run.id
    except IntegrityError:
        return None


def record_skipped(settings: Settings, schedule_id: str, starts: list[datetime]) -> list[str]:
    """Record the periods ``starts`` as ``skipped`` in one transaction (a savepoint each: a
    period another claimant has is left to it); the ids of the rows inserted."""
    if not starts:
        return []
    inserted: list[str] = []
    with transaction(settings.sqlalchemy_url) as session:
        schedule = session.get(Schedule, schedule_id)
        if schedule is None:
            return []
        for start in starts:
            run = ScheduleRun(
                organisation_id=schedule.organisation_id,
                schedule_id=schedule.id,
                period_start=as_utc(start),
                kind="scheduled",
                status=ScheduleRunStatus.SKIPPED,
                reason=f"skipped by the catch-up policy {schedule.catch_up!r}: the scheduler "
                "was not running when the period started",
                created_at=utc_now(),
                finished_at=utc_now(),
            )
            try:
                with session.begin_nested():
                    session.add(run)
                    session.flush()
            except IntegrityError:
                continue
            inserted.append(run.id)
        newest = as_utc(max(starts))
        if schedule.last_period_start is None or as_utc(schedule.last_period_start) < newest:
            schedule.last_period_start = newest
    return inserted


def _fetch(settings: Settings, schedule: Schedule) -> tuple[ReceivedFile, str, Any] | None:
    """The new file of a directory or URL source: ``(received, filename, marker)``, or None."""
    source = schedule.source
    if source.get("kind") == "directory":
        directory = schedule_sources.check_directory(settings, source["directory"])
        found = schedule_sources.newest_directory_file(settings, directory, schedule.source_marker)
        if found is None:
            return None
        return schedule_sources.receive_directory_file(settings, found), found.name, found.marker
    received = schedule_sources.fetch_url(settings, source["url"])
    if schedule.source_marker and schedule.source_marker.get("sha256") == received.sha256:
        storage.remove_file(received.path)
        return None
    filename = source["url"].rsplit("/", 1)[-1].split("?", 1)[0] or None
    return received, filename or "fetched", {"sha256": received.sha256}


def _newest_upload(
    session: Session, schedule: Schedule, site: Site, until: datetime, *, any_age: bool = False
) -> Scan | None:
    """The newest scan of the site (not its reference) that arrived before ``until`` and, unless
    ``any_age`` (a manual run), after the last one this schedule compared."""
    statement = (
        select(Scan)
        .where(Scan.site_id == site.id, Scan.created_at <= until)
        .order_by(Scan.created_at.desc(), Scan.id.desc())
        .limit(1)
    )
    if not any_age:
        since = as_utc(schedule.last_scan_at or schedule.created_at)
        statement = statement.where(Scan.created_at > since)
    if site.reference_scan_id is not None:
        statement = statement.where(Scan.id != site.reference_scan_id)
    return session.scalar(statement)


def _missed_reason(schedule: Schedule, site: Site, run: ScheduleRun, until: datetime) -> str:
    """Why run ``run`` had no scan to compare, in one sentence that says what to do."""
    kind = schedule.source.get("kind")
    if kind == "directory":
        return (
            f"no new file in {schedule.source['directory']} since the last one taken: drop the "
            "next scan there (copy it under a *.part name and rename it when complete)"
        )
    if kind == "url":
        return (
            f"{schedule.source['url']} served the same file as the last run (same SHA-256): "
            "publish the next scan there"
        )
    if run.kind == "manual":
        return (
            f"site {site.name!r} has no scan besides its reference: upload one with "
            f"POST /api/v1/sites/{site.id}/scans"
        )
    since = as_utc(schedule.last_scan_at or schedule.created_at)
    return (
        f"no scan of site {site.name!r} arrived between {iso_utc(since)} and {iso_utc(until)}: "
        f"upload one with POST /api/v1/sites/{site.id}/scans, or run the schedule now "
        f"(POST /api/v1/schedules/{schedule.id}/run) to compare the newest scan"
    )


def _existing_job(
    session: Session,
    site: Site,
    reference: str,
    scan: str,
    detector: tuple[str, str, dict[str, Any]],
) -> Job | None:
    """The newest job of the pair that ran ``detector`` (method, variant and parameters)."""
    method, variant, params = detector
    candidates = session.scalars(
        select(Job)
        .where(
            Job.site_id == site.id,
            Job.reference_scan_id == reference,
            Job.scan_id == scan,
            Job.method == method,
            Job.variant == variant,
        )
        .order_by(Job.created_at.desc())
    ).all()
    return next((job for job in candidates if (job.params or {}) == params), None)


def _job_for(
    session: Session, settings: Settings, schedule: Schedule, site: Site, reference: str, scan: str
) -> Job:
    """The job comparing ``scan`` with ``reference`` by the schedule's detector: an existing one
    with the same method, variant and parameters (an upload's own job), else a new one."""
    detector = schedule.detector or {}
    method, variant, params = sites.resolve_detector(
        site, detector.get("method"), detector.get("variant"), detector.get("params")
    )
    existing = _existing_job(session, site, reference, scan, (method, variant, params))
    if existing is not None:
        return existing
    return jobs.new_job(
        session,
        settings,
        schedule_principal(schedule),
        site_id=site.id,
        reference_scan_id=reference,
        scan_id=scan,
        method=method,
        variant=variant,
        params=params,
    )


def _previous_scan(session: Session, site: Site, scan: Scan) -> Scan | None:
    return session.scalar(
        select(Scan)
        .where(Scan.site_id == site.id, Scan.id != scan.id, Scan.created_at <= scan.created_at)
        .order_by(Scan.created_at.desc(), Scan.id.desc())
        .limit(1)
    )


def _compare(
    session: Session, settings: Settings, schedule: Schedule, run: ScheduleRun, scan: Scan
) -> None:
    site = session.get(Site, schedule.site_id)
    if site is None or site.reference_scan_id is None:
        raise ConflictError(
            "the site has no reference scan: upload one with ?reference=true", code="no_reference"
        )
    job = _job_for(session, settings, schedule, site, site.reference_scan_id, scan.id)
    run.job_id = job.id
    if schedule.compare_previous:
        previous = _previous_scan(session, site, scan)
        if previous is not None and previous.id != site.reference_scan_id:
            run.trend_job_id = _job_for(session, settings, schedule, site, previous.id, scan.id).id
    run.scan_id = scan.id
    run.status = ScheduleRunStatus.COMPARED
    run.reason = None
    schedule.missed_since = None  # a comparison ends the missed spell
    last_at = as_utc(schedule.last_scan_at) if schedule.last_scan_at is not None else None
    if last_at is None or as_utc(scan.created_at) >= last_at:
        schedule.last_scan_id = scan.id
        schedule.last_scan_at = as_utc(scan.created_at)


def site_of_event(site: Site | None, site_id: str) -> dict[str, Any]:
    """The site as an event body names it (as the job events do): ``{"id", "name"}``."""
    return {"id": site_id, "name": site.name if site is not None else None}


def _finish_missed(session: Session, schedule: Schedule, run: ScheduleRun, reason: str) -> None:
    """Record ``run`` missed with ``reason``; publish ``schedule.missed`` once per missed spell."""
    run.status = ScheduleRunStatus.MISSED
    run.reason = reason
    claimed = session.execute(
        update(Schedule)
        .where(Schedule.id == schedule.id, Schedule.missed_since.is_(None))
        .values(missed_since=as_utc(run.period_start))
    )
    if claimed.rowcount != 1:  # type: ignore[attr-defined]
        return  # the spell's event was published already
    publish_event(
        session,
        organisation_id=schedule.organisation_id,
        event_type="schedule.missed",
        payload={
            "schedule_id": schedule.id,
            "site_id": schedule.site_id,
            "site": site_of_event(session.get(Site, schedule.site_id), schedule.site_id),
            "run_id": run.id,
            "period_start": iso_utc(run.period_start),
            "reason": reason,
        },
    )


def _record_failure(settings: Settings, run_id: str, error: str) -> None:
    with transaction(settings.sqlalchemy_url) as session:
        run = session.get(ScheduleRun, run_id)
        if run is not None:
            run.status = ScheduleRunStatus.FAILED
            run.error = error[:2000]
            run.finished_at = utc_now()


def _take_marker(settings: Settings, schedule_id: str, marker: Any) -> bool:
    """Note ``marker`` as the source's last file unless another run did; whether this one did.

    Taken before the file is stored: a file that cannot be stored (malformed, over the quota)
    fails its run once and is not tried again; the next new file is.
    """
    with transaction(settings.sqlalchemy_url) as session:
        schedule = session.get(Schedule, schedule_id, with_for_update=True)
        if schedule is None or schedule.source_marker == marker:
            return False
        schedule.source_marker = marker
        return True


def complete_period(settings: Settings, run_id: str) -> ScheduleRun:
    """Run a claimed period: take its scan, compare, or record it missed (or failed, raising)."""
    with transaction(settings.sqlalchemy_url) as session:
        run = session.get(ScheduleRun, run_id)
        schedule = session.get(Schedule, run.schedule_id) if run is not None else None
        if run is None or schedule is None:
            raise NotFoundError(f"schedule run {run_id} not found")
        session.expunge(schedule)
    try:
        fetched = None if schedule.source.get("kind") == "uploads" else _fetch(settings, schedule)
        if fetched is not None and not _take_marker(settings, schedule.id, fetched[2]):
            storage.remove_file(fetched[0].path)  # another run took this very file meanwhile
            fetched = None
        with transaction(settings.sqlalchemy_url) as session:
            scan: Scan | None = None
            if fetched is not None:
                received, filename, _marker = fetched
                scan = schedule_ingest.store_received_scan(
                    session,
                    settings,
                    schedule_principal(schedule),
                    schedule.site_id,
                    received,
                    filename,
                )
            run = session.get_one(ScheduleRun, run_id)
            # Locked: runs of one schedule finish one at a time, each seeing the last's marks.
            schedule = session.get_one(Schedule, schedule.id, with_for_update=True)
            site = session.get_one(Site, schedule.site_id)
            until = as_utc(run.period_start) if run.kind == "scheduled" else utc_now()
            if schedule.source.get("kind") == "uploads":
                # "Run now" compares at once: the newest scan, even one older than the schedule.
                manual = run.kind == "manual"
                scan = _newest_upload(session, schedule, site, until, any_age=manual)
            if scan is None:
                _finish_missed(session, schedule, run, _missed_reason(schedule, site, run, until))
            else:
                _compare(session, settings, schedule, run, scan)
            run.finished_at = utc_now()
            return run
    except AppError as exc:
        _record_failure(settings, run_id, exc.detail)
        raise
    except Exception as exc:
        _record_failure(settings, run_id, f"{type(exc).__name__}: {exc}")
        raise


def run_manual(settings: Settings, schedule_id: str) -> ScheduleRun:
    """Run a schedule now, outside its rhythm (its source's refusals are raised)."""
    run_id = claim_period(settings, schedule_id, utc_now(), "manual", ScheduleRunStatus.RUNNING)
    if run_id is None:
        raise NotFoundError(f"schedule {schedule_id} not found")
    return complete_period(settings, run_id)


def plan_periods(schedule: Schedule, now: datetime) -> tuple[list[datetime], list[datetime]]:
    """The due periods of ``schedule`` at ``now``: ``(to_run, to_skip)`` by its catch-up."""
    after = as_utc(schedule.last_period_start or schedule.created_at)
    due = rhythm_of(schedule).starts_between(after, now, MAX_PERIODS_PER_TICK)
    if not due or schedule.catch_up == "each":
        return due, []
    if schedule.catch_up == "latest":
        return due[-1:], due[:-1]
    on_time = timedelta(seconds=ON_TIME_SECONDS)
    to_run = [start for start in due if now - start <= on_time]
    return to_run, [start for start in due if now - start > on_time]


def _tick_schedule(
    settings: Settings, schedule: Schedule, now: datetime, report: TickReport
) -> None:
    to_run, to_skip = plan_periods(schedule, now)
    for run_id in record_skipped(settings, schedule.id, to_skip):
        report.skipped += 1
        report.add(ScheduleRunStatus.SKIPPED, run_id)
    for start in to_run:
        run_id = claim_period(settings, schedule.id, start, "scheduled", ScheduleRunStatus.RUNNING)
        if run_id is None:
            continue
        try:
            run = complete_period(settings, run_id)
        except Exception as exc:
            logger.warning(
                "schedule run failed: %s", exc, extra={"schedule_id": schedule.id, "run_id": run_id}
            )
            report.add(ScheduleRunStatus.FAILED, run_id)
            continue
        report.add(run.status, run_id)


def check_stale(settings: Settings, schedule_id: str, now: datetime) -> bool:
    """Publish ``site.stale`` when the site has had no scan for ``stale_after_seconds`` (once
    per spell; a new scan ends the spell); whether it was published now."""
    with transaction(settings.sqlalchemy_url) as session:
        schedule = session.get(Schedule, schedule_id)
        if schedule is None or schedule.stale_after_seconds is None:
            return False
        newest = session.scalar(
            select(func.max(Scan.created_at)).where(Scan.site_id == schedule.site_id)
        )
        last_arrival = as_utc(newest or schedule.created_at)
        if now - last_arrival < timedelta(seconds=schedule.stale_after_seconds):
            if schedule.stale_since is not None:
                schedule.stale_since = None  # a scan arrived: the spell is over
            return False
        claimed = session.execute(
            update(Schedule)
            .where(Schedule.id == schedule.id, Schedule.stale_since.is_(None))
            .values(stale_since=now)
        )
        if claimed.rowcount != 1:  # type: ignore[attr-defined]
            return False
        publish_event(
            session,
            organisation_id=schedule.organisation_id,
            event_type="site.stale",
            payload={
                "site_id": schedule.site_id,
                "site": site_of_event(session.get(Site, schedule.site_id), schedule.site_id),
                "schedule_id": schedule.id,
                "last_scan_at": iso_utc(last_arrival) if newest is not None else None,
                "stale_after_seconds": schedule.stale_after_seconds,
            },
        )
        return True


def abandoned_after(settings: Settings) -> timedelta:
    """How long a run may stay ``running`` before it counts as left by a process that died.

    A run does one fetch (at most the fetch timeout) and a few commits; five fetch timeouts,
    and never under ten minutes, is far beyond any live run.
    """
    return timedelta(seconds=max(600.0, 5 * settings.schedule_fetch_timeout_seconds))


def fail_abandoned_runs(settings: Settings) -> list[str]:
    """Mark ``failed`` the runs still ``running`` long after their claim; their ids.

    Their period is not run again (the claim is the once-only guard); the failure says why, so
    that the runs list does not show a run in progress for ever. Measured on the wall clock (a
    tick's ``now`` may be a chosen period time; a run's claim time is always the wall clock's).
    """
    now = utc_now()
    claimed_before = now - abandoned_after(settings)
    with transaction(settings.sqlalchemy_url) as session:
        abandoned = session.scalars(
            select(ScheduleRun.id).where(
                ScheduleRun.status == ScheduleRunStatus.RUNNING,
                ScheduleRun.created_at < claimed_before,
            )
        ).all()
        if abandoned:
            session.execute(
                update(ScheduleRun)
                .where(
                    ScheduleRun.id.in_(abandoned), ScheduleRun.status == ScheduleRunStatus.RUNNING
                )
                .values(
                    status=ScheduleRunStatus.FAILED,
                    error="interrupted: the process running it stopped before it finished; "
                    "the period is not run again (run the schedule now to compare at once)",
                    finished_at=now,
                )
            )
    return list(abandoned)


def tick(settings: Settings, now: datetime | None = None) -> TickReport:
    """Run every enabled schedule's due periods and staleness check at ``now`` (default: now)."""
    now = as_utc(now or utc_now())
    report = TickReport()
    for run_id in fail_abandoned_runs(settings):
        report.add(ScheduleRunStatus.FAILED, run_id)
    with transaction(settings.sqlalchemy_url) as session:
        schedules = session.scalars(
            select(Schedule).where(Schedule.enabled.is_(True)).order_by(Schedule.created_at)
        ).all()
        session.expunge_all()
    for schedule in schedules:
        try:
            _tick_schedule(settings, schedule, now, report)
            if check_stale(settings, schedule.id, now):
                report.stale += 1
        except Exception:
            logger.exception("schedule tick failed", extra={"schedule_id": schedule.id})
    return report
