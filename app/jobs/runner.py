"""What a worker runs for each queue message: the job, and its message again if it needs one.

The one module that knows both the queue and the execution (``queue`` and ``execution`` know
nothing of each other); worker processes install :func:`run_job_from_queue` as the queue's job
runner (:func:`app.jobs.queue.install_job_runner`) and :func:`run_tile_from_queue` as its tile
runner (one tile of a job compared tile by tile, :mod:`app.jobs.tiles`) and
:func:`run_crop_pass_from_queue` as its crop pass runner (:mod:`app.jobs.crop_passes`).
"""

from __future__ import annotations

from app.config import Settings, get_settings
from app.jobs.crop_passes import run_crop_pass_message
from app.jobs.execution import execute_job
from app.jobs.leases import JobOutcome
from app.jobs.limits import job_memory_limit, job_threads, memory_limit
from app.jobs.queue import (
    install_crop_pass_runner,
    install_job_runner,
    install_tile_runner,
    send_job_message,
)
from app.jobs.tiles import run_tile_message


def run_job_once(job_id: str, settings: Settings) -> JobOutcome:
    """Run job ``job_id`` if it still needs running; send its message again if it went back to
    ``queued`` (a failed attempt with attempts left).  The outcome of :func:`execute_job`."""
    outcome = execute_job(job_id, settings)
    if outcome == JobOutcome.QUEUED:
        send_job_message(job_id, settings)
    return outcome


def run_job_from_queue(job_id: str) -> None:
    """The job runner of worker processes: settings from the environment."""
    run_job_once(job_id, get_settings())


def run_tile_from_queue(job_id: str, tile_index: int) -> None:
    """The tile runner of worker processes: one tile of a job, under the job's memory cap."""
    settings = get_settings()
    with memory_limit(job_memory_limit(settings)):
        run_tile_message(job_id, tile_index, settings, threads=job_threads(settings))


def run_crop_pass_from_queue(job_id: str, pass_index: int) -> None:
    """The crop pass runner of worker processes: one cloud's crop pass of a streamed job,
    under the job's memory cap."""
    settings = get_settings()
    with memory_limit(job_memory_limit(settings)):
        run_crop_pass_message(job_id, pass_index, settings)


def install() -> None:
    """Make this process run the jobs, tiles and crop passes whose messages it takes (a worker
    calls this at start)."""
    install_job_runner(run_job_from_queue)
    install_tile_runner(run_tile_from_queue)
    install_crop_pass_runner(run_crop_pass_from_queue)
