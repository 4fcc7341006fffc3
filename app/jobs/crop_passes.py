"""A streamed job's crops pass fanned out on the queue: one pass a cloud, any worker runs one.

The parent of a streamed tiled job (:func:`app.jobs.execution.streamed_compute`) writes every
tile's crop of both clouds from the files before any tile runs.  Each cloud's pass
(:class:`app.core.tiling.crop_passes.CropPass`) reads its own file and writes its own crop files,
so the two are independent.  :class:`CropPassFanOut`, the parent's crop runner:

1. saves the plan, the context and each pass under ``results/<job_id>/tiles/crop-passes/``
   and puts the job's ``job_crop_pass`` rows (one a cloud) back to ``queued``: each attempt
   of the job writes its crops afresh (its parent empties the crops directory first);
2. sends one ``run_crop_pass(job_id, pass_index)`` message per pass on the queue the workers
   already consume (:func:`app.jobs.queue.send_crop_pass_messages`);
3. runs passes itself like any other worker (as many at once as its threads) until none is
   left, then waits for the passes others are running.

A pass writes into a directory of its own beside the crops and moves its files into place
only when all are written, so a worker killed mid-pass leaves no half-written crop where the
tiles read.  The claim, the lease, the retry of a killed worker's pass, the storing (only
under a lease still held) and the cancelling with the job are the tiles'
(:mod:`app.jobs.task_rows`): a pass is never run again once ``succeeded`` in an attempt.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import shutil
import time
import uuid
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from sqlalchemy import delete, select

from app.config import Settings
from app.core.files import write_atomically
from app.core.tiling.crop_passes import CropPass, write_crop_pass
from app.core.tiling.crops import crop_file
from app.core.tiling.plan import TilePlan
from app.core.tiling.tile import TileContext
from app.db.models import JobCropPass, JobStatus, TileStatus
from app.db.session import transaction
from app.jobs.hooks import job_hooks
from app.jobs.leases import ClaimedJob, LeaseKeeper, TileOutcome, make_lease_owner
from app.jobs.queue import send_crop_pass_messages
from app.jobs.task_rows import (
    CROP_PASSES,
    TaskLease,
    cancel_tasks,
    claim_task,
    held,
    job_status,
    store_task,
)
from app.jobs.tiles import WAIT_SECONDS, PhaseTimings

logger = logging.getLogger("scandiff.jobs.crop_passes")

PASSES_DIR = "crop-passes"
"""Under a job's tiles directory: what the passes read (plan, context, one file a pass)."""
PARTIAL_CROPS_DIR = "crops.partial"
"""Under a job's tiles directory: where the passes write the crops (the parent then swaps it
in as ``crops``, :mod:`app.core.tiling.streamed`)."""

ProgressCallback = Callable[[str, float], None]


def _pass_file(directory: Path, pass_index: int) -> Path:
    return directory / PASSES_DIR / f"pass-{pass_index}.npz"


def save_pass_inputs(
    settings: Settings,
    directory: Path,
    plan: TilePlan,
    context: TileContext,
    passes: Sequence[CropPass],
) -> None:
    """Write what the passes read under ``directory`` (a job's tiles directory); each pass's
    file as stored in the database (relative to the data directory)."""
    (directory / PASSES_DIR).mkdir(parents=True, exist_ok=True)
    write_atomically(directory / PASSES_DIR / "plan.npz", plan.save)
    write_atomically(directory / PASSES_DIR / "context.npz", context.save)
    for pass_index, crop_pass in enumerate(passes):
        stored = dataclasses.replace(
            crop_pass,
            path=Path(settings.data_layout.stored_form(crop_pass.path)),
            other_path=None
            if crop_pass.other_path is None
            else Path(settings.data_layout.stored_form(crop_pass.other_path)),
        )
        write_atomically(_pass_file(directory, pass_index), stored.save)


def load_pass_inputs(
    settings: Settings, directory: Path, pass_index: int
) -> tuple[TilePlan, TileContext, CropPass]:
    """The plan, the context and pass ``pass_index`` a parent saved (its file resolved here)."""
    crop_pass = CropPass.load(_pass_file(directory, pass_index))
    return (
        TilePlan.load(directory / PASSES_DIR / "plan.npz"),
        TileContext.load(directory / PASSES_DIR / "context.npz"),
        dataclasses.replace(
            crop_pass,
            path=settings.data_layout.resolve(str(crop_pass.path)),
            other_path=None
            if crop_pass.other_path is None
            else settings.data_layout.resolve(str(crop_pass.other_path)),
        ),
    )


def reset_passes(settings: Settings, job_id: str, n_passes: int) -> None:
    """The job's pass rows, ``queued`` afresh (attempts kept): this attempt writes its crops."""
    with transaction(settings.sqlalchemy_url) as session:
        rows = {
            row.pass_index: row
            for row in session.scalars(select(JobCropPass).where(JobCropPass.job_id == job_id))
        }
        for pass_index in range(n_passes):
            row = rows.get(pass_index)
            if row is None:
                session.add(
                    JobCropPass(job_id=job_id, pass_index=pass_index, status=TileStatus.QUEUED)
                )
            else:
                row.status, row.lease_owner, row.lease_expires_at = TileStatus.QUEUED, None, None
        session.execute(
            delete(JobCropPass).where(
                JobCropPass.job_id == job_id, JobCropPass.pass_index >= n_passes
            )
        )


def passes_left(settings: Settings, job_id: str) -> int:
    """How many of a job's passes are not ``succeeded``."""
    with transaction(settings.sqlalchemy_url) as session:
        return len(
            session.scalars(
                select(JobCropPass.pass_index).where(
                    JobCropPass.job_id == job_id, JobCropPass.status != TileStatus.SUCCEEDED
                )
            ).all()
        )


def _still_held(settings: Settings, job_id: str, pass_index: int, owner: str) -> bool:
    with transaction(settings.sqlalchemy_url) as session:
        row = session.scalar(
            select(JobCropPass.pass_index).where(held(CROP_PASSES, job_id, pass_index, owner))
        )
    return row is not None


def run_claimed_pass(
    settings: Settings,
    job_id: str,
    pass_index: int,
    owner: str,
    *,
    parent: ClaimedJob | None = None,
) -> bool:
    """Run a crop pass this worker claimed and store it; whether it was stored."""
    directory = settings.data_layout.job_tiles_dir(job_id)
    partial = directory / PARTIAL_CROPS_DIR
    started = time.perf_counter()
    with TaskLease(settings, CROP_PASSES, job_id, pass_index, owner):
        job_hooks.in_crop_pass(parent, pass_index)
        plan, context, crop_pass = load_pass_inputs(settings, directory, pass_index)
        own = partial / f".{crop_pass.side}-{uuid.uuid4().hex}"
        own.mkdir()  # not its parents: a crops directory removed since is not made again
        try:
            sizes = write_crop_pass(own, plan, context, crop_pass)
            if _still_held(settings, job_id, pass_index, owner):  # else another ran it anew
                for tile_index in range(plan.n_tiles):
                    os.replace(
                        crop_file(own, tile_index, crop_pass.side),
                        crop_file(partial, tile_index, crop_pass.side),
                    )
        finally:
            shutil.rmtree(own, ignore_errors=True)
    stored = store_task(
        settings,
        CROP_PASSES,
        job_id,
        pass_index,
        owner,
        points=int(sizes.sum()),
        seconds=time.perf_counter() - started,
    )
    logger.info(
        "crop pass %s",
        "stored" if stored else "written but not stored (lease lost or job stopped)",
        extra={"job_id": job_id, "stage": f"crop-pass-{pass_index}"},
    )
    return stored


def run_crop_pass_message(job_id: str, pass_index: int, settings: Settings) -> TileOutcome:
    """What a worker does with one ``run_crop_pass`` message; what happened."""
    owner = make_lease_owner()
    claimed = claim_task(settings, CROP_PASSES, job_id, owner, pass_index)
    if claimed is None:
        if job_status(settings, job_id) in (JobStatus.RUNNING, JobStatus.QUEUED):
            return TileOutcome.SKIPPED
        cancel_tasks(settings, CROP_PASSES, job_id)  # finished, failed or deleted
        return TileOutcome.CANCELLED
    stored = run_claimed_pass(settings, job_id, claimed, owner)
    return TileOutcome.COMPUTED if stored else TileOutcome.CANCELLED


class CropPassFanOut:
    """A streamed job's crop runner in a worker (:data:`app.core.tiling.crop_passes.CropRunner`):
    the passes on the queue, this worker among those running them.

    Parameters
    ----------
    job : ClaimedJob
    settings : Settings
    keeper : LeaseKeeper
        The job's heartbeat, checked between passes.
    timings : PhaseTimings
        The job's phases (shared with its :class:`~app.jobs.tiles.TileFanOut`).
    """

    def __init__(
        self, job: ClaimedJob, settings: Settings, keeper: LeaseKeeper, timings: PhaseTimings
    ) -> None:
        self.job, self.settings, self.keeper, self.timings = job, settings, keeper, timings
        self.owner = make_lease_owner()

    def __call__(
        self,
        directory: Path,
        plan: TilePlan,
        context: TileContext,
        passes: Sequence[CropPass],
        threads: int,
        report: ProgressCallback,
    ) -> None:
        """Every pass run by whichever worker took it, its crop files in ``directory``."""
        tiles_dir = self.settings.data_layout.job_tiles_dir(self.job.id)
        if Path(directory) != tiles_dir / PARTIAL_CROPS_DIR:
            raise ValueError(f"the passes write into {tiles_dir / PARTIAL_CROPS_DIR}")
        with self.timings.phase("crop_pass_inputs_write"):
            save_pass_inputs(self.settings, tiles_dir, plan, context, passes)
            reset_passes(self.settings, self.job.id, len(passes))
            send_crop_pass_messages(self.job.id, list(range(len(passes))), self.settings)
        computed_here = self._take_passes(len(passes), max(1, threads))
        with transaction(self.settings.sqlalchemy_url) as session:
            rows = session.execute(
                select(JobCropPass.lease_owner, JobCropPass.seconds).where(
                    JobCropPass.job_id == self.job.id
                )
            ).all()
        elsewhere = [row.seconds or 0.0 for row in rows if row.lease_owner != self.owner]
        self.timings.seconds["crop_passes_other_workers"] = float(sum(elsewhere))
        self.timings.seconds["crop_passes_computed_here"] = float(computed_here)
        self.timings.seconds["crop_passes_computed_elsewhere"] = float(len(elsewhere))

    def _take_passes(self, n_passes: int, threads: int) -> int:
        """Run passes here (up to ``threads`` at once) until every pass is done by someone;
        how many were stored here."""
        computed_here = 0
        while True:
            self.keeper.check()
            if passes_left(self.settings, self.job.id) == 0:
                return computed_here
            claimed: list[int] = []
            while len(claimed) < threads:
                taken = claim_task(self.settings, CROP_PASSES, self.job.id, self.owner)
                if taken is None:
                    break
                claimed.append(taken)
            if not claimed:
                with self.timings.phase("crop_passes_parent_waiting"):
                    time.sleep(WAIT_SECONDS)  # others are running the last passes
                continue
            with (
                self.timings.phase("crop_passes_parent_computing"),
                ThreadPoolExecutor(max_workers=len(claimed)) as pool,
            ):
                stored = pool.map(
                    lambda index: run_claimed_pass(
                        self.settings, self.job.id, index, self.owner, parent=self.job
                    ),
                    claimed,
                )
                computed_here += sum(int(done) for done in stored)


__all__ = [
    "PARTIAL_CROPS_DIR",
    "PASSES_DIR",
    "CropPassFanOut",
    "load_pass_inputs",
    "passes_left",
    "reset_passes",
    "run_claimed_pass",
    "run_crop_pass_message",
    "save_pass_inputs",
]
