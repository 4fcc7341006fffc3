"""Running one job: claim, compute outside any transaction, write the files, store once.

A worker (:func:`execute_job`):

1. **claims** the job and keeps its lease alive from a heartbeat thread
   (:mod:`app.jobs.leases`);
2. reads the scans and runs the comparison **outside any transaction**, under an ``RLIMIT_AS``
   cap and with the job's thread budget (:mod:`app.jobs.limits`);
3. writes ``results/<job_id>/labels.npz`` and ``details.npz`` **atomically** and stores the
   results in **one short transaction**, only if it still holds the lease
   (:mod:`app.jobs.results`).

Input problems (:class:`app.core.errors.InputError`) fail the job at once with the message; other
errors put it back to ``queued`` until ``max_attempts`` is reached: the caller
(:func:`app.jobs.runner.run_job_once`) then sends its message again.  Tests reach in only through
:data:`app.jobs.hooks.job_hooks`.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from typing import Any

import numpy as np

from app.config import Settings
from app.core.allocator import release_freed_memory_promptly
from app.core.errors import InputError
from app.core.formats import read_point_cloud
from app.core.trajectory_store import with_stored_trajectory
from app.jobs.geometry import geometry_cache_of, record_geometry_cache
from app.jobs.hooks import job_hooks
from app.jobs.leases import (
    PROGRESS_COMPARED,
    PROGRESS_LOADED,
    ClaimedJob,
    LeaseKeeper,
    LeaseLostError,
    claim_job,
    fail_job,
    job_log,
    make_lease_owner,
    release_job,
)
from app.jobs.limits import job_memory_limit, job_threads, memory_limit
from app.jobs.results import store_results, write_result_files

logger = logging.getLogger("scandiff.jobs")


def compute(
    job: ClaimedJob, settings: Settings, keeper: LeaseKeeper
) -> tuple[Any, dict[str, float]]:
    """Read both scans and run ``compare``; the result and this job's own timings."""
    release_freed_memory_promptly()  # freed temporaries go back to the system: peak = live data
    job_hooks.inject_faults(job, keeper)
    compare = job_hooks.comparison()
    if job.reference_path is None or job.scan_path is None:
        raise InputError("the job's reference scan or scan no longer exists")
    keeper.report("loading", 0.0)
    started = time.perf_counter()
    threads = job_threads(settings)  # the result does not depend on it
    reference = read_point_cloud(job.reference_path, format=job.reference_format, threads=threads)
    scan = read_point_cloud(job.scan_path, format=job.scan_format, threads=threads)
    reference = with_stored_trajectory(reference, job.reference_path)  # if one was given
    scan = with_stored_trajectory(scan, job.scan_path)
    # The origin given at upload wins over the file's; a job's params override both.
    if job.reference_sensor_origin is not None:
        reference = dataclasses.replace(
            reference, sensor_origin=np.asarray(job.reference_sensor_origin, dtype=np.float64)
        )
    if job.scan_sensor_origin is not None:
        scan = dataclasses.replace(
            scan, sensor_origin=np.asarray(job.scan_sensor_origin, dtype=np.float64)
        )
    load_seconds = time.perf_counter() - started
    keeper.report("comparing", PROGRESS_LOADED)
    cache = geometry_cache_of(job)
    result = compare(
        reference,
        scan,
        method=job.method,
        variant=job.variant,
        params=job.params,  # replayable: holds align/random_state/stage parameters when given
        progress=keeper.compare_progress,
        threads=threads,
        site_calibration=job.site_calibration,  # learned from the site's reviewed jobs
        geometry_cache=cache,
    )
    if cache is not None:
        record_geometry_cache(job, settings, cache)
    return result, {"load_inputs": load_seconds}


def execute_job(job_id: str, settings: Settings) -> str:
    """Run job ``job_id`` once if it needs running; the outcome.

    Outcomes: ``succeeded``, ``failed``, ``queued`` (to be retried: the caller sends its message
    again), ``skipped`` (duplicate message, finished or leased elsewhere), ``lease-lost`` (taken
    over; nothing written).
    """
    owner = make_lease_owner()
    job = claim_job(job_id, settings, owner)
    if job is None:
        return "skipped"
    keeper = LeaseKeeper(job, settings).start()
    started = time.perf_counter()
    limit_bytes = job_memory_limit(settings)
    try:
        with memory_limit(limit_bytes):
            result, job_timings = compute(job, settings, keeper)
            keeper.report("writing", PROGRESS_COMPARED)
            write_started = time.perf_counter()
            labels_path = write_result_files(job, settings, result)
            job_timings["write_outputs"] = time.perf_counter() - write_started
        keeper.report("storing", PROGRESS_COMPARED)
        keeper.stop()
        keeper.check()
        job_timings["job_total"] = time.perf_counter() - started
        timings = {**dict(result.timings), **job_timings}
        if not store_results(job, settings, result, labels_path, timings):
            job_log("job lease lost before storing; nothing stored", job.id, "lease-lost")
            return "lease-lost"
        job_log(
            "job succeeded",
            job.id,
            "succeeded",
            attempt=job.attempt,
            seconds=round(job_timings["job_total"], 3),
            n_regions=len(result.regions),
            changed=bool(result.changed),
        )
        return "succeeded"
    except LeaseLostError:
        job_log("job lease lost; nothing stored", job.id, "lease-lost", attempt=job.attempt)
        return "lease-lost"
    except InputError as exc:
        keeper.stop()
        return "failed" if fail_job(job, settings, str(exc)) else "lease-lost"
    except MemoryError:
        keeper.stop()
        message = (
            f"out of memory: the job needs more than the worker's memory cap "
            f"(SCANDIFF_JOB_MEMORY_LIMIT_BYTES={limit_bytes})"
            if limit_bytes
            else "out of memory"
        )
        return "failed" if fail_job(job, settings, message) else "lease-lost"
    except KeyboardInterrupt:
        keeper.stop()
        release_job(job, settings, "interrupted by a worker shutdown", count_attempt=False)
        raise
    except Exception as exc:
        keeper.stop()
        logger.exception("job attempt failed", extra={"job_id": job.id, "stage": keeper.stage})
        return release_job(job, settings, f"{type(exc).__name__}: {exc}", count_attempt=True)
    finally:
        keeper.stop()
