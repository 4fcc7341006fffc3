"""The recovery sweep: nothing the ``job`` table says must run is left without a queue message.

Huey is at-most-once: a worker killed mid-job loses its message.  The sweep, run by ``scandiff
serve`` at start-up and by the consumer every ``recovery_interval_seconds``:

* puts ``running`` jobs whose lease expired (or whose worker was a process of this host that
  no longer exists) back to ``queued`` and sends a message, or fails them with a reason when
  their attempts are used up (a poison job ends here instead of looping);
* sends a message again for ``queued`` jobs that have none waiting in the queue and were not
  enqueued within the grace period (``job_lease_seconds``: a dequeued message is claimed within
  milliseconds), or were never enqueued (``enqueued_at`` null);
* deletes temporary result files left by killed workers, and the tile inputs of jobs that no
  longer run (a worker killed between storing a tiled job's labels and removing its crops);
* deletes events (and their webhook deliveries) past ``event_retention_days`` whose deliveries
  are all final (:mod:`app.jobs.retention`).

When the queue cannot be reached (Redis down) the jobs whose message could not be sent keep
``enqueued_at`` null, so the first sweep after the queue is back sends them: an upload accepted
while Redis was down runs without any manual step.  Sending a message twice is harmless: a
worker's claim is idempotent.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from datetime import datetime, timedelta

from sqlalchemy import or_, select

from app.clock import as_utc, utc_now
from app.config import Settings
from app.db.models import Job, JobStatus
from app.db.session import transaction
from app.jobs.alerts.events import publish_job_finished
from app.jobs.leases import job_log, lease_owner_is_dead_here
from app.jobs.queue import mark_not_enqueued, pending_job_ids, send_job_message
from app.jobs.results import remove_finished_tile_inputs, remove_stale_temp_files
from app.jobs.retention import prune_events

logger = logging.getLogger("scandiff.jobs.recovery")

TEMP_FILE_MAX_AGE_SECONDS = 3600.0
"""Temporary result files older than this belong to dead workers (used by periodic sweeps)."""


@dataclass
class RecoveryReport:
    """What one sweep did."""

    requeued_expired: list[str] = field(default_factory=list)
    failed_expired: list[str] = field(default_factory=list)
    resent_queued: list[str] = field(default_factory=list)
    unsent: list[str] = field(default_factory=list)
    """Jobs due a message that the queue did not take (unreachable); the next sweep sends them."""
    removed_temp_files: int = 0
    removed_tile_inputs: int = 0
    """Jobs whose left-over tile inputs were deleted (a worker killed after storing, a failure)."""
    pruned_events: int = 0

    @property
    def enqueued(self) -> list[str]:
        """Every job id a message was sent for."""
        unsent = set(self.unsent)
        return [job_id for job_id in self.due_messages if job_id not in unsent]

    @property
    def due_messages(self) -> list[str]:
        """Every job id the sweep found needing a message."""
        return [*self.requeued_expired, *self.resent_queued]

    def is_empty(self) -> bool:
        """Whether the sweep changed nothing."""
        return not (
            self.due_messages
            or self.failed_expired
            or self.removed_temp_files
            or self.removed_tile_inputs
            or self.pruned_events
        )


def recover_expired_leases(settings: Settings, now: datetime, report: RecoveryReport) -> None:
    """Requeue (or fail, when used up) running jobs whose worker is gone; one transaction.

    A worker is gone when its lease expired, or at once when it was a process of this host
    that no longer exists (a crash seen without waiting for the lease).
    """
    with transaction(settings.sqlalchemy_url) as session:
        running = (
            session.execute(
                select(Job).where(Job.status == JobStatus.RUNNING).with_for_update(skip_locked=True)
            )
            .scalars()
            .all()
        )
        for job in running:
            lease_expires_at = as_utc(job.lease_expires_at)
            if lease_expires_at is not None and lease_expires_at >= now:
                if not lease_owner_is_dead_here(job.lease_owner):
                    continue
                why = "its worker process is gone"
            else:
                why = "its lease expired"
            lost = (
                f"attempt {job.attempts} stopped without finishing ({why}: {job.lease_owner}; "
                f"worker killed or lost) at stage {job.stage}"
            )
            if job.attempts >= job.max_attempts:
                job.status = JobStatus.FAILED
                job.error = (
                    f"gave up after {job.attempts} attempts (max_attempts={job.max_attempts}): "
                    f"{lost}"
                )
                job.stage = "failed"
                job.finished_at = now
                report.failed_expired.append(job.id)
            else:
                job.status = JobStatus.QUEUED
                job.error = lost
                job.stage = "requeued"
                job.enqueued_at = now
                report.requeued_expired.append(job.id)
            job.lease_owner = None
            job.lease_expires_at = None
        for job_id in report.failed_expired:
            publish_job_finished(session, job_id)  # job.failed, same transaction
    for job_id in report.failed_expired:
        job_log("job failed: attempts used up", job_id, "failed")
    for job_id in report.requeued_expired:
        job_log("job lease expired; requeued", job_id, "requeued")


def resend_orphaned_queued(
    settings: Settings, now: datetime, pending: set[str] | None, report: RecoveryReport
) -> None:
    """Mark queued jobs without a live message as re-enqueued now; one transaction."""
    grace_cutoff = now - timedelta(seconds=settings.job_lease_seconds)
    with transaction(settings.sqlalchemy_url) as session:
        candidates = (
            session.execute(
                select(Job)
                .where(
                    Job.status == JobStatus.QUEUED,
                    or_(Job.enqueued_at.is_(None), Job.enqueued_at < grace_cutoff),
                )
                .with_for_update(skip_locked=True)
            )
            .scalars()
            .all()
        )
        for job in candidates:
            if pending is not None and job.id in pending and job.enqueued_at is not None:
                continue  # its message is still waiting in the queue
            job.enqueued_at = now
            report.resent_queued.append(job.id)
    for job_id in report.resent_queued:
        job_log("queued job had no message; enqueued again", job_id, "requeued")


def send_due_messages(settings: Settings, report: RecoveryReport) -> None:
    """Send the messages the sweep found due; on the first failure (queue unreachable) note the
    rest as not enqueued, so that the next sweep sends them at once."""
    due = report.due_messages
    for index, job_id in enumerate(due):
        try:
            send_job_message(job_id, settings)
        except Exception as exc:
            report.unsent = due[index:]
            logger.warning(
                "queue unreachable (%s: %s); %d job(s) stay queued for the next sweep",
                type(exc).__name__,
                exc,
                len(report.unsent),
                extra={"stage": "recovery"},
            )
            mark_not_enqueued(report.unsent, settings)
            return


def recovery_sweep(
    settings: Settings, *, temp_file_max_age_seconds: float = TEMP_FILE_MAX_AGE_SECONDS
) -> RecoveryReport:
    """Run one sweep (see the module docstring) and send the messages; what it did."""
    report = RecoveryReport()
    now = utc_now()
    try:
        pending: set[str] | None = pending_job_ids(settings)
    except Exception:  # cannot list the queue: fall back to the grace period alone
        logger.exception("cannot list queued messages; re-sending by age only")
        pending = None
    recover_expired_leases(settings, now, report)
    resend_orphaned_queued(settings, now, pending, report)
    send_due_messages(settings, report)
    report.removed_temp_files = remove_stale_temp_files(settings, temp_file_max_age_seconds)
    report.removed_tile_inputs = remove_finished_tile_inputs(settings)
    report.pruned_events = prune_events(settings, now)
    if not report.is_empty():
        logger.info(
            "recovery sweep",
            extra={
                "requeued_expired": len(report.requeued_expired),
                "failed_expired": len(report.failed_expired),
                "resent_queued": len(report.resent_queued),
                "unsent": len(report.unsent),
                "removed_temp_files": report.removed_temp_files,
                "removed_tile_inputs": report.removed_tile_inputs,
                "pruned_events": report.pruned_events,
            },
        )
    return report
