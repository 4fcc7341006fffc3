"""The lease protocol of a job: claim, heartbeat, lease owner, and giving the job back.

The ``job`` table is the truth; a queue message only says "look at job X".  A worker **claims**
the job with one conditional ``UPDATE`` (``status='queued'``, or ``'running'`` with an expired
lease, and ``attempts < max_attempts``) that increments ``attempts`` and takes a lease
(``lease_owner``, ``lease_expires_at``); a duplicate message for a finished job or a job leased
by a live worker changes nothing.  A **heartbeat** thread (:class:`LeaseKeeper`) keeps the lease
alive and writes ``progress``/``stage``; if the lease was taken over, the job is abandoned at the
next progress report.  Every later write (:func:`fail_job`, :func:`release_job`, and
:func:`app.jobs.results.store_results`) applies only while the lease is still ours
(:func:`held_by`).
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import uuid
from dataclasses import dataclass
from datetime import datetime, timedelta
from enum import StrEnum
from pathlib import Path
from typing import Any

from sqlalchemy import ColumnElement, and_, or_, select, update
from sqlalchemy.orm import Session

from app.clock import utc_now
from app.config import Settings
from app.db.models import Job, JobStatus, Scan, Site
from app.db.session import transaction
from app.jobs.alerts.events import publish_job_finished
from app.kit.data_layout import StoredPathError
from app.log import job_request_id, remember_job_request_id

logger = logging.getLogger("scandiff.jobs")

MIN_HEARTBEAT_SPACING_SECONDS = 0.2
"""Stage changes wake the heartbeat early, but never write more often than this."""

# Share of the job's progress bar before and after ``compare``.
PROGRESS_LOADED = 0.05
PROGRESS_COMPARED = 0.95


class LeaseLostError(RuntimeError):
    """Another worker took this job over (our lease expired); abandon it without writing."""


def make_lease_owner() -> str:
    """A lease-owner name for this worker attempt: ``host:pid:random``."""
    return f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:8]}"


def lease_owner_pid(lease_owner: str | None) -> int | None:
    """The process id inside a lease-owner name (None if not of the form ``host:pid:random``)."""
    if not lease_owner:
        return None
    parts = lease_owner.rsplit(":", 2)
    return int(parts[1]) if len(parts) == 3 and parts[1].isdigit() else None


def lease_owner_is_dead_here(lease_owner: str | None) -> bool:
    """Whether ``lease_owner`` names a process of this host that no longer runs.

    Lets the sweep recover a crashed local worker's job without waiting for its lease.  Only a
    definite "no such process" counts: a reused pid reads as alive (then the lease decides).
    """
    if not lease_owner:
        return False
    host, _, _ = lease_owner.rpartition(":")
    host, _, pid_text = host.rpartition(":")
    if host != socket.gethostname() or not pid_text.isdigit():
        return False
    pid = int(pid_text)
    if pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        return False
    try:  # a zombie (killed, not yet reaped by its parent) is dead too
        with open(f"/proc/{pid}/stat") as stat_file:
            stat = stat_file.read()
        return stat[stat.rindex(")") + 2 :].split()[0] in ("Z", "X")
    except OSError:
        return False


def claimable(now: datetime) -> ColumnElement[bool]:
    """SQL condition: the job may be taken (queued, or running with an expired lease)."""
    return or_(
        Job.status == JobStatus.QUEUED,
        and_(
            Job.status == JobStatus.RUNNING,
            or_(Job.lease_expires_at.is_(None), Job.lease_expires_at < now),
        ),
    )


def held_by(job_id: str, owner: str) -> ColumnElement[bool]:
    """SQL condition: job ``job_id`` is running under ``owner``'s lease."""
    return and_(Job.id == job_id, Job.status == JobStatus.RUNNING, Job.lease_owner == owner)


class JobOutcome(StrEnum):
    """What one run of a job's message did (:func:`app.jobs.execution.execute_job`)."""

    SUCCEEDED = "succeeded"
    FAILED = "failed"
    QUEUED = "queued"
    """The attempt failed with attempts left: the job is queued again (its message is resent)."""
    SKIPPED = "skipped"
    """Nothing to run: a duplicate message, a job already finished or leased elsewhere."""
    LEASE_LOST = "lease-lost"
    """Another worker took the job over; nothing was written."""


class TileOutcome(StrEnum):
    """What one ``run_tile`` message did (:func:`app.jobs.tiles.run_tile_message`)."""

    COMPUTED = "computed"
    SKIPPED = "skipped"
    """Done, or taken by a live worker; or the job waits for its next worker, who resumes it."""
    CANCELLED = "cancelled"
    """The job no longer runs (finished, failed or deleted): its open tiles are cancelled."""


@dataclass(frozen=True)
class ClaimedJob:
    """What a worker needs to run a job it has claimed."""

    id: str
    attempt: int
    max_attempts: int
    lease_owner: str
    method: str
    variant: str
    params: dict[str, Any]
    reference_path: Path | None
    reference_format: str | None
    scan_path: Path | None
    scan_format: str | None
    scan_filename: str | None
    reference_sensor_origin: list[float] | list[list[float]] | None = None
    """One origin, or one per station of a merged cloud (as stored on the scan)."""
    scan_sensor_origin: list[float] | list[list[float]] | None = None
    request_id: str | None = None
    """The id of the API request that created the job (carried by its log lines)."""
    site_calibration: dict[str, Any] | None = None
    """The site's thresholds learned from reviewed jobs, as they were when the job was claimed."""
    reference_scan_id: str | None = None
    reference_sha256: str | None = None
    """The reference scan's id and file checksum (its geometry cache's key, app.jobs.geometry)."""
    storage_problem: str | None = None
    """Why a scan's stored path cannot be read (it leads outside the data directory); the job
    fails with it."""


def scan_paths(
    settings: Settings, reference: Scan | None, scan: Scan | None
) -> tuple[tuple[Path | None, Path | None], str | None]:
    """The files of a job's reference and scan (None: deleted), checked; and what is wrong."""
    try:
        return (
            settings.data_layout.resolve(reference.storage_path) if reference else None,
            settings.data_layout.resolve(scan.storage_path) if scan else None,
        ), None
    except StoredPathError as exc:
        return (None, None), str(exc)


def job_log(message: str, job_id: str, stage: str, **fields: Any) -> None:
    """One structured log line about a job stage (with its creating request's id when known)."""
    request_id = job_request_id(job_id)
    if request_id is not None:
        fields.setdefault("request_id", request_id)
    logger.info(message, extra={"job_id": job_id, "stage": stage, **fields})


def claim_job(
    job_id: str, settings: Settings, owner: str, now: datetime | None = None
) -> ClaimedJob | None:
    """Atomically take job ``job_id`` for ``owner``; None if it needs no run (or is used up)."""
    with transaction(settings.sqlalchemy_url) as session:
        session.connection()  # SQLite: BEGIN IMMEDIATE waits for the write lock here, so ...
        now = now or utc_now()  # ... a lease is never born expired by that wait
        lease_until = now + timedelta(seconds=settings.job_lease_seconds)
        claimed = session.execute(
            update(Job)
            .where(Job.id == job_id, Job.attempts < Job.max_attempts, claimable(now))
            .values(
                status=JobStatus.RUNNING,
                attempts=Job.attempts + 1,
                lease_owner=owner,
                lease_expires_at=lease_until,
                started_at=now,
                finished_at=None,
                stage="claimed",
                progress=0.0,
            )
            .execution_options(synchronize_session=False)
        ).rowcount
        job = session.get(Job, job_id, populate_existing=True)
        if job is None:
            logger.warning("job not found", extra={"job_id": job_id, "stage": "skipped"})
            return None
        remember_job_request_id(job.id, job.request_id)  # for every later line about the job
        if not claimed:
            give_up_if_used_up(session, job, now)
            return None
        reference = session.get(Scan, job.reference_scan_id)
        scan = session.get(Scan, job.scan_id)
        site = session.get(Site, job.site_id)
        stored_paths, storage_problem = scan_paths(settings, reference, scan)
        claimed_job = ClaimedJob(
            id=job.id,
            attempt=job.attempts,
            max_attempts=job.max_attempts,
            lease_owner=owner,
            method=job.method,
            variant=job.variant,
            params=dict(job.params or {}),
            reference_path=stored_paths[0],
            reference_format=reference.format if reference else None,
            scan_path=stored_paths[1],
            scan_format=scan.format if scan else None,
            scan_filename=scan.filename if scan else None,
            reference_sensor_origin=reference.sensor_origin if reference else None,
            scan_sensor_origin=scan.sensor_origin if scan else None,
            request_id=job.request_id,
            site_calibration=dict(site.calibration) if site and site.calibration else None,
            reference_scan_id=reference.id if reference else None,
            reference_sha256=reference.sha256 if reference else None,
            storage_problem=storage_problem,
        )
    job_log(
        "job claimed",
        job_id,
        "claimed",
        attempt=claimed_job.attempt,
        max_attempts=claimed_job.max_attempts,
        lease_owner=owner,
    )
    return claimed_job


def give_up_if_used_up(session: Session, job: Job, now: datetime) -> bool:
    """Inside a claim: fail a claimable job whose attempts are used up; True if it did."""
    reason = (
        f"gave up after {job.attempts} attempts (max_attempts={job.max_attempts}): "
        f"{job.error or 'each attempt stopped without finishing (worker killed or lost)'}"
    )
    failed = session.execute(
        update(Job)
        .where(Job.id == job.id, Job.attempts >= Job.max_attempts, claimable(now))
        .values(
            status=JobStatus.FAILED,
            error=reason,
            stage="failed",
            finished_at=now,
            lease_expires_at=None,
        )
        .execution_options(synchronize_session=False)
    ).rowcount
    if failed:
        publish_job_finished(session, job.id)  # job.failed, in the claim's transaction
        job_log("job failed", job.id, "failed", attempt=job.attempts, error=reason)
    else:
        logger.info(
            "job message ignored (duplicate, finished or leased elsewhere)",
            extra={"job_id": job.id, "stage": "skipped", "status": job.status},
        )
    return bool(failed)


class LeaseKeeper:
    """Heartbeat thread: extends the lease and writes progress/stage; notices a lost lease."""

    def __init__(self, job: ClaimedJob, settings: Settings) -> None:
        self.job = job
        self.settings = settings
        self.stage = "claimed"
        self.progress = 0.0
        self.lost = threading.Event()
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"lease-{job.id[:8]}", daemon=True)

    def start(self) -> LeaseKeeper:
        """Start heart-beating."""
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop heart-beating (idempotent)."""
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join()

    def check(self) -> None:
        """Raise :class:`LeaseLostError` if another worker took the job over."""
        if self.lost.is_set():
            raise LeaseLostError(f"job {self.job.id}: lease of {self.job.lease_owner} was lost")

    def report(self, stage: str, progress: float) -> None:
        """Note the job's stage and overall progress (0..1); logs each new stage once."""
        self.check()
        progress = min(max(float(progress), 0.0), 1.0)
        if stage != self.stage:
            self.stage = stage
            self.progress = progress
            job_log(
                "job stage",
                self.job.id,
                stage,
                attempt=self.job.attempt,
                progress=round(progress, 3),
            )
            self._wake.set()
        else:
            self.progress = progress

    def compare_progress(self, stage: str, fraction: float) -> None:
        """``compare``'s progress callback, mapped into the compare share of the job."""
        fraction = min(max(float(fraction), 0.0), 1.0)
        self.report(stage, PROGRESS_LOADED + (PROGRESS_COMPARED - PROGRESS_LOADED) * fraction)

    def beat(self) -> bool:
        """Extend the lease and store progress once; False if the lease is no longer ours."""
        now = utc_now()
        with transaction(self.settings.sqlalchemy_url) as session:
            updated = session.execute(
                update(Job)
                .where(held_by(self.job.id, self.job.lease_owner))
                .values(
                    lease_expires_at=now + timedelta(seconds=self.settings.job_lease_seconds),
                    progress=self.progress,
                    stage=self.stage[:32],
                )
                .execution_options(synchronize_session=False)
            ).rowcount
        return bool(updated)

    def _run(self) -> None:
        """Beat every ``job_heartbeat_seconds`` (sooner on a stage change) until stopped."""
        interval = self.settings.job_heartbeat_seconds
        while not self._stop.is_set():
            self._wake.wait(interval)
            self._wake.clear()
            if self._stop.is_set():
                return
            try:
                if not self.beat():
                    self.lost.set()
                    logger.warning(
                        "job lease lost; abandoning this attempt",
                        extra={"job_id": self.job.id, "stage": "lease-lost"},
                    )
                    return
            except Exception:  # a failed beat is retried; the lease covers several intervals
                logger.exception(
                    "job heartbeat failed", extra={"job_id": self.job.id, "stage": self.stage}
                )
            self._stop.wait(MIN_HEARTBEAT_SPACING_SECONDS)


def fail_job(job: ClaimedJob, settings: Settings, message: str) -> bool:
    """Mark the job ``failed`` with ``message`` if we still hold it; True if we did."""
    with transaction(settings.sqlalchemy_url) as session:
        failed = session.execute(
            update(Job)
            .where(held_by(job.id, job.lease_owner))
            .values(
                status=JobStatus.FAILED,
                error=message,
                stage="failed",
                finished_at=utc_now(),
                lease_expires_at=None,
            )
            .execution_options(synchronize_session=False)
        ).rowcount
        if failed:
            publish_job_finished(session, job.id)  # job.failed, same transaction
    if failed:
        job_log("job failed", job.id, "failed", attempt=job.attempt, error=message)
    return bool(failed)


def release_job(
    job: ClaimedJob, settings: Settings, error: str, *, count_attempt: bool
) -> JobOutcome:
    """Give the job back (``queued``) or fail it when attempts are used up; the new status.

    ``count_attempt=False`` (shutdown interrupted the attempt) does not use up an attempt and
    leaves ``enqueued_at`` empty so the next recovery sweep sends the message again.
    """
    with transaction(settings.sqlalchemy_url) as session:
        row = session.execute(
            select(Job).where(held_by(job.id, job.lease_owner)).with_for_update()
        ).scalar_one_or_none()
        if row is None:
            return JobOutcome.LEASE_LOST
        if count_attempt and row.attempts >= row.max_attempts:
            row.status = JobStatus.FAILED
            row.error = f"failed after {row.attempts} attempts; last error: {error}"
            row.finished_at = utc_now()
            row.stage = "failed"
        else:
            row.status = JobStatus.QUEUED
            row.error = error
            row.stage = "requeued"
            row.enqueued_at = utc_now() if count_attempt else None
            if not count_attempt:
                row.attempts = max(0, row.attempts - 1)
        row.lease_owner = None
        row.lease_expires_at = None
        status = row.status
        final_error = row.error
        if status == JobStatus.FAILED:
            publish_job_finished(session, job.id)  # job.failed, same transaction
    job_log(f"job {status}", job.id, status, attempt=job.attempt, error=final_error)
    return JobOutcome(str(status))
