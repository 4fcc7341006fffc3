"""A large job's tiles fanned out on the queue: any worker takes a tile, none is done twice.

A job whose pair does not fit one worker's memory budget is localised tile by tile
(:func:`app.core.tiling.compare_tiled`).  Its worker (the *parent*) hands the tiles to the
queue with :class:`TileFanOut`, the tile runner it passes to ``compare_tiled``:

1. it writes the tiles' inputs under ``results/<job_id>/tiles/`` (the plan, the shared
   context, and each tile's own crop of both clouds, cut in one pass over the points:
   :mod:`app.core.tiling.crops`, so a tile reads its crop and nothing else) and records one
   ``job_tile`` row per tile;
2. it sends one ``run_tile(job_id, tile_index)`` message per tile still to do, on the queue
   the workers already consume (:func:`app.jobs.queue.send_tile_messages`);
3. it takes tiles itself like any other worker until none is left, then waits for the tiles
   others are running, and merges.

Each tile is claimed with one conditional ``UPDATE`` (``queued``, or ``running`` with an expired
lease) that takes a lease kept alive by a heartbeat thread.  So:

* a worker killed mid-tile leaves a ``running`` row whose lease expires; the parent (or
  any other worker's message) takes it again: **retried**;
* a tile whose row is ``succeeded`` and whose result file exists is **never recomputed**,
  even by a new parent after the first one was killed (the plan of the same inputs is the
  same);
* a tile of a job no longer running (failed, finished, deleted with its site) is
  **cancelled**: messages for it are dropped, and a tile being computed is not stored (a
  job waiting in the queue for its next attempt keeps its tiles: that attempt resumes them).

No scheduler of its own: the queue carries the messages, the table is the truth, and the
parent's wait is the only loop (it sleeps on the table while other workers finish).
"""

from __future__ import annotations

import logging
import shutil
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from sqlalchemy import func, select

from app.config import Settings
from app.core.files import write_atomically
from app.core.tiling import TileContext, TilePlan, TileResult, TileSource, compute_tile
from app.core.tiling.crops import TileCropFiles, write_tile_crops
from app.core.tiling.pair_files import StoredTileResults
from app.db.models import JobStatus, JobTile, TileStatus
from app.db.session import transaction
from app.jobs.hooks import job_hooks
from app.jobs.leases import ClaimedJob, LeaseKeeper, TileOutcome, make_lease_owner
from app.jobs.queue import send_tile_messages
from app.jobs.task_rows import (
    CROP_PASSES,
    TILES,
    TaskLease,
    cancel_tasks,
    claim_task,
    job_status,
    store_task,
)
from app.kit.allocator import return_free_heap

logger = logging.getLogger("scandiff.jobs.tiles")

PLAN_FILE = "plan.npz"
CONTEXT_FILE = "context.npz"
CROPS_DIR = "crops"
"""Under a job's tiles directory: each tile's crop of each cloud (:mod:`app.core.tiling.crops`)."""
WAIT_SECONDS = 0.25
"""How long the parent sleeps between looks at the table while other workers finish tiles."""

ProgressCallback = Callable[[str, float], None]


def save_tile_inputs(
    directory: Path, plan: TilePlan, source: TileSource | TileCropFiles, context: TileContext
) -> None:
    """Write what the tiles read into ``directory``: each tile's own crop files, the plan and
    the context (the plan last: a tile reads nothing before the parent recorded the tiles)."""
    directory.mkdir(parents=True, exist_ok=True)
    if isinstance(source, TileCropFiles):  # a streamed parent wrote them from the files
        if source.directory != directory / CROPS_DIR:
            raise ValueError(f"the tiles' crops must be in {directory / CROPS_DIR}")
        write_atomically(directory / PLAN_FILE, plan.save)
        write_atomically(directory / CONTEXT_FILE, context.save)
        return
    partial = directory / f"{CROPS_DIR}.partial"  # swapped in whole: a tile of an earlier
    shutil.rmtree(partial, ignore_errors=True)  # attempt never reads a half-written crop
    write_tile_crops(partial, plan, source, context)
    shutil.rmtree(directory / CROPS_DIR, ignore_errors=True)
    partial.rename(directory / CROPS_DIR)
    write_atomically(directory / PLAN_FILE, plan.save)
    write_atomically(directory / CONTEXT_FILE, context.save)


def load_tile_inputs(directory: Path) -> tuple[TilePlan, TileCropFiles, TileContext]:
    """The plan, the tiles' crop files and the context a parent saved."""
    return (
        TilePlan.load(directory / PLAN_FILE),
        TileCropFiles(directory / CROPS_DIR),
        TileContext.load(directory / CONTEXT_FILE),
    )


def tile_result_path(directory: Path, tile_index: int) -> Path:
    """Where tile ``tile_index``'s result file lives."""
    return directory / f"tile-{tile_index:05d}.npz"


def record_tiles(settings: Settings, job_id: str, plan: TilePlan) -> list[int]:
    """Rows for the plan's tiles (kept when present); the tiles still to compute.

    A ``succeeded`` row whose result file is gone goes back to ``queued``.
    """
    directory = settings.data_layout.job_tiles_dir(job_id)
    with transaction(settings.sqlalchemy_url) as session:
        existing = {
            tile.tile_index: tile
            for tile in session.scalars(select(JobTile).where(JobTile.job_id == job_id))
        }
        for tile_index in range(plan.n_tiles):
            tile = existing.get(tile_index)
            if tile is None:
                session.add(JobTile(job_id=job_id, tile_index=tile_index, status=TileStatus.QUEUED))
            elif tile.status == TileStatus.SUCCEEDED and not (
                tile.result_path and settings.data_layout.resolve(tile.result_path).exists()
            ):
                tile.status, tile.result_path = TileStatus.QUEUED, None
            elif tile.status == TileStatus.CANCELLED:
                tile.status = TileStatus.QUEUED
        for tile_index, tile in existing.items():
            if tile_index >= plan.n_tiles:  # a different plan: should not happen, never kept
                session.delete(tile)
        session.flush()
        todo = session.scalars(
            select(JobTile.tile_index).where(
                JobTile.job_id == job_id, JobTile.status != TileStatus.SUCCEEDED
            )
        ).all()
    directory.mkdir(parents=True, exist_ok=True)
    return sorted(todo)


def tile_progress(settings: Settings, job_id: str) -> tuple[int, int]:
    """``(tiles done, tiles in all)`` of a job (``(0, 0)`` when it is not tiled)."""
    with transaction(settings.sqlalchemy_url) as session:
        rows = session.execute(
            select(JobTile.status, func.count())
            .where(JobTile.job_id == job_id)
            .group_by(JobTile.status)
        ).all()
    counts = {status: count for status, count in rows}
    return counts.get(TileStatus.SUCCEEDED, 0), sum(counts.values())


def claim_tile(
    settings: Settings, job_id: str, owner: str, tile_index: int | None = None
) -> int | None:
    """Take one tile of a running job (that one, or the lowest free one); its index, or None
    (:func:`app.jobs.task_rows.claim_task`)."""
    return claim_task(settings, TILES, job_id, owner, tile_index)


def run_claimed_tile(
    settings: Settings,
    job_id: str,
    tile_index: int,
    owner: str,
    threads: int | None = None,
    *,
    parent: ClaimedJob | None = None,
    tiles_done_here: int = 0,
) -> bool:
    """Compute a tile this worker claimed and store it; whether it was stored."""
    directory = settings.data_layout.job_tiles_dir(job_id)
    started = time.perf_counter()
    with TaskLease(settings, TILES, job_id, tile_index, owner):
        job_hooks.in_tile(parent, tiles_done_here)
        return_free_heap()  # sized by the budget: it starts from live data (not a crop pass's)
        plan, source, context = load_tile_inputs(directory)
        result = compute_tile(plan, tile_index, source, context, threads=threads)
        path = tile_result_path(directory, tile_index)
        write_atomically(path, result.save)
    seconds = time.perf_counter() - started
    crop_points = int(
        result.figures.get("crop_reference_points", 0) + result.figures.get("crop_scan_points", 0)
    )
    stored = store_task(
        settings,
        TILES,
        job_id,
        tile_index,
        owner,
        result_path=settings.data_layout.stored_form(path),
        points=crop_points,
        seconds=seconds,
    )
    logger.info(
        "tile %s",
        "stored" if stored else "computed but not stored (lease lost or job stopped)",
        extra={"job_id": job_id, "stage": f"tile-{tile_index}"},
    )
    return bool(stored)


def cancel_tiles(settings: Settings, job_id: str) -> int:
    """Mark a stopped job's unfinished tiles and crop passes ``cancelled``; how many."""
    return sum(cancel_tasks(settings, table, job_id) for table in (TILES, CROP_PASSES))


def remove_tile_inputs(settings: Settings, job_id: str) -> None:
    """Delete a finished job's tile files (its merged labels are stored; rows stay as a record)."""
    directory = settings.data_layout.job_tiles_dir(job_id)
    if directory.is_dir():
        shutil.rmtree(directory, ignore_errors=True)


def run_tile_message(
    job_id: str, tile_index: int, settings: Settings, threads: int | None = None
) -> TileOutcome:
    """What a worker does with one ``run_tile`` message; what happened (for logs and tests)."""
    owner = make_lease_owner()
    claimed = claim_tile(settings, job_id, owner, tile_index)
    if claimed is None:
        status = job_status(settings, job_id)
        if status in (JobStatus.RUNNING, JobStatus.QUEUED):
            return TileOutcome.SKIPPED
        cancel_tiles(settings, job_id)  # finished, failed or deleted: nothing will read it
        return TileOutcome.CANCELLED
    stored = run_claimed_tile(settings, job_id, claimed, owner, threads)
    return TileOutcome.COMPUTED if stored else TileOutcome.CANCELLED


def largest_first(plan: TilePlan, tile_indices: list[int]) -> list[int]:
    """``tile_indices`` with the largest planned crops first (ties by index).

    The longest tiles start first, so the last tile to finish is a short one and the workers
    finish together (the result does not depend on the order).
    """
    return sorted(tile_indices, key=lambda index: (-int(plan.crop_points[index]), index))


class PhaseTimings:
    """Wall and CPU seconds of a job's named phases, summed over their runs.

    ``seconds[name]`` (wall) and ``seconds[name + "_cpu"]`` (this process's CPU, all its
    threads), for the job's ``timings``.
    """

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    @contextmanager
    def phase(self, name: str) -> Iterator[None]:
        """Add the wall and CPU seconds of the ``with`` block to phase ``name``."""
        wall, cpu = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            for key, spent in (
                (name, time.perf_counter() - wall),
                (f"{name}_cpu", time.process_time() - cpu),
            ):
                self.seconds[key] = self.seconds.get(key, 0.0) + spent


class TileFanOut:
    """``compare_tiled``'s tile runner in a worker: tiles on the queue, this worker in the pool.

    Parameters
    ----------
    job : ClaimedJob
        The job this worker holds.
    settings : Settings
    keeper : LeaseKeeper
        The job's heartbeat: checked between tiles (a lost lease abandons the job) and fed
        the tiles' progress.
    """

    def __init__(self, job: ClaimedJob, settings: Settings, keeper: LeaseKeeper) -> None:
        self.job, self.settings, self.keeper = job, settings, keeper
        self.owner = make_lease_owner()
        self.computed_here = 0
        self.timings = PhaseTimings()

    def __call__(
        self,
        plan: TilePlan,
        source: TileSource | TileCropFiles,
        context: TileContext,
        threads: int,
        report: ProgressCallback,
    ) -> Sequence[TileResult]:
        """Every tile's result, in order, computed by whichever worker took it (read from its
        file when the merge asks for it)."""
        directory = self.settings.data_layout.job_tiles_dir(self.job.id)
        with self.timings.phase("tile_inputs_write"):
            save_tile_inputs(directory, plan, source, context)
            todo = largest_first(plan, record_tiles(self.settings, self.job.id, plan))
            send_tile_messages(self.job.id, todo, self.settings)
        with self.timings.phase("tiles_parent"):
            self._take_tiles(todo, threads, report)
        with self.timings.phase("tile_results_read"):
            with transaction(self.settings.sqlalchemy_url) as session:
                rows = session.execute(
                    select(JobTile.result_path, JobTile.lease_owner, JobTile.seconds)
                    .where(JobTile.job_id == self.job.id)
                    .order_by(JobTile.tile_index)
                ).all()
            results = StoredTileResults(  # read when merged, one at a time
                [self.settings.data_layout.resolve(str(row.result_path)) for row in rows]
            )
        elsewhere = [row.seconds or 0.0 for row in rows if row.lease_owner != self.owner]
        self.timings.seconds["tiles_other_workers"] = float(sum(elsewhere))
        self.timings.seconds["tiles_computed_here"] = float(self.computed_here)
        self.timings.seconds["tiles_computed_elsewhere"] = float(len(elsewhere))
        return results

    def _take_tiles(self, order: list[int], threads: int, report: ProgressCallback) -> None:
        """Compute tiles here (in ``order`` first) until every tile is done by someone."""
        preferred = list(order)
        while True:
            self.keeper.check()
            done, total = tile_progress(self.settings, self.job.id)
            report("localise", 0.35 + 0.5 * done / max(1, total))
            if done == total:
                return
            claimed = None
            while claimed is None and preferred:
                claimed = claim_tile(self.settings, self.job.id, self.owner, preferred.pop(0))
            if claimed is None:  # the rest are taken: any whose worker died, else wait
                claimed = claim_tile(self.settings, self.job.id, self.owner)
            if claimed is None:
                with self.timings.phase("tiles_parent_waiting"):
                    time.sleep(WAIT_SECONDS)  # others are running the last tiles
                continue
            with self.timings.phase("tiles_parent_computing"):
                stored = run_claimed_tile(
                    self.settings,
                    self.job.id,
                    claimed,
                    self.owner,
                    threads,
                    parent=self.job,
                    tiles_done_here=self.computed_here,
                )
            self.computed_here += int(stored)


__all__ = [
    "PhaseTimings",
    "TileFanOut",
    "cancel_tiles",
    "claim_tile",
    "largest_first",
    "load_tile_inputs",
    "record_tiles",
    "remove_tile_inputs",
    "run_tile_message",
    "save_tile_inputs",
    "tile_progress",
]
