"""Rows of a job's parts that any worker may run: claimed with a lease, retried, cancelled.

A fanned-out job's tiles (``job_tile``, :mod:`app.jobs.tiles`) and a streamed job's crop
passes (``job_crop_pass``, :mod:`app.jobs.crop_passes`) are run the same way; a
:class:`TaskTable` names the table and its index column, and the functions here do the rest:

* :func:`claim_task`: one conditional ``UPDATE`` takes a ``queued`` row, or a ``running`` one
  whose lease expired (its worker died), for a job still running, with a fresh lease;
* :class:`TaskLease`: a heartbeat thread extends the lease while the part runs;
* :func:`store_task`: the part is ``succeeded`` only if this worker still holds it (a worker
  that lost its lease, or whose job stopped, stores nothing);
* :func:`cancel_tasks`: a stopped job's open rows are ``cancelled``.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass
from datetime import timedelta
from typing import Any

from sqlalchemy import ColumnElement, and_, or_, select, update
from sqlalchemy.orm import InstrumentedAttribute

from app.clock import utc_now
from app.config import Settings
from app.db.models import Job, JobCropPass, JobStatus, JobTile, TileStatus
from app.db.session import transaction

logger = logging.getLogger("scandiff.jobs.tasks")


@dataclass(frozen=True)
class TaskTable:
    """A table of a job's parts: its model and the column numbering a job's parts."""

    model: type[JobTile] | type[JobCropPass]
    index: InstrumentedAttribute[int]


TILES = TaskTable(JobTile, JobTile.tile_index)
CROP_PASSES = TaskTable(JobCropPass, JobCropPass.pass_index)


def claim_task(
    settings: Settings, table: TaskTable, job_id: str, owner: str, index: int | None = None
) -> int | None:
    """Take one part of a running job (that one, or the lowest free one); its index, or None.

    Free: ``queued``, or ``running`` with an expired lease (its worker died).
    """
    model = table.model
    with transaction(settings.sqlalchemy_url) as session:
        session.connection()  # SQLite: BEGIN IMMEDIATE waits for the write lock here, so ...
        now = utc_now()  # ... a lease is never born expired by that wait
        free = or_(
            model.status == TileStatus.QUEUED,
            and_(model.status == TileStatus.RUNNING, model.lease_expires_at < now),
        )
        job_running = session.scalar(
            select(Job.id).where(Job.id == job_id, Job.status == JobStatus.RUNNING)
        )
        if job_running is None:
            return None
        candidates = select(table.index).where(model.job_id == job_id, free)
        if index is not None:
            candidates = candidates.where(table.index == index)
        for candidate in session.scalars(candidates.order_by(table.index).limit(4)):
            taken = session.execute(
                update(model)
                .where(model.job_id == job_id, table.index == candidate, free)
                .values(
                    status=TileStatus.RUNNING,
                    attempts=model.attempts + 1,
                    lease_owner=owner,
                    lease_expires_at=now + timedelta(seconds=settings.job_lease_seconds),
                    started_at=now,
                )
                .execution_options(synchronize_session=False)
            ).rowcount
            if taken:
                return int(candidate)
    return None


def held(table: TaskTable, job_id: str, index: int, owner: str) -> ColumnElement[bool]:
    """The part, still running under ``owner``'s lease."""
    model = table.model
    return and_(
        model.job_id == job_id,
        table.index == index,
        model.status == TileStatus.RUNNING,
        model.lease_owner == owner,
    )


class TaskLease:
    """Heartbeat thread of one claimed part: extends its lease until stopped."""

    def __init__(
        self, settings: Settings, table: TaskTable, job_id: str, index: int, owner: str
    ) -> None:
        self.settings, self.table, self.job_id, self.index, self.owner = (
            settings,
            table,
            job_id,
            index,
            owner,
        )
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="task-lease", daemon=True)

    def __enter__(self) -> TaskLease:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    def _run(self) -> None:
        interval = min(self.settings.job_heartbeat_seconds, self.settings.job_lease_seconds / 3)
        while not self._stop.wait(interval):
            try:
                with transaction(self.settings.sqlalchemy_url) as session:
                    session.execute(
                        update(self.table.model)
                        .where(held(self.table, self.job_id, self.index, self.owner))
                        .values(
                            lease_expires_at=utc_now()
                            + timedelta(seconds=self.settings.job_lease_seconds)
                        )
                        .execution_options(synchronize_session=False)
                    )
            except Exception:  # retried at the next beat; the lease covers several
                logger.exception("task heartbeat failed", extra={"job_id": self.job_id})


def store_task(
    settings: Settings, table: TaskTable, job_id: str, index: int, owner: str, **values: Any
) -> bool:
    """Mark a part this worker still holds ``succeeded`` with ``values``; whether it was.

    ``lease_owner`` stays (who computed it); the lease's expiry is cleared.
    """
    with transaction(settings.sqlalchemy_url) as session:
        return bool(
            session.execute(
                update(table.model)
                .where(held(table, job_id, index, owner))
                .values(
                    status=TileStatus.SUCCEEDED,
                    finished_at=utc_now(),
                    lease_expires_at=None,
                    **values,
                )
                .execution_options(synchronize_session=False)
            ).rowcount
        )


def cancel_tasks(settings: Settings, table: TaskTable, job_id: str) -> int:
    """Mark a stopped job's unfinished parts ``cancelled``; how many."""
    model = table.model
    with transaction(settings.sqlalchemy_url) as session:
        return session.execute(
            update(model)
            .where(
                model.job_id == job_id,
                model.status.in_([TileStatus.QUEUED, TileStatus.RUNNING]),
            )
            .values(status=TileStatus.CANCELLED, lease_owner=None, lease_expires_at=None)
            .execution_options(synchronize_session=False)
        ).rowcount


def job_status(settings: Settings, job_id: str) -> str | None:
    """A job's status (None once deleted)."""
    with transaction(settings.sqlalchemy_url) as session:
        return session.scalar(select(Job.status).where(Job.id == job_id))


__all__ = [
    "CROP_PASSES",
    "TILES",
    "TaskLease",
    "TaskTable",
    "cancel_tasks",
    "claim_task",
    "held",
    "job_status",
    "store_task",
]
