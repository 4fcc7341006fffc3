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
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from app.config import DEFAULT_MEMORY_BUDGET_BYTES, Settings
from app.core.errors import InputError
from app.core.formats import read_point_cloud
from app.jobs.crop_passes import CropPassFanOut
from app.jobs.geometry import geometry_cache_of, record_geometry_cache
from app.jobs.hooks import job_hooks
from app.jobs.leases import (
    PROGRESS_COMPARED,
    PROGRESS_LOADED,
    ClaimedJob,
    JobOutcome,
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
from app.jobs.tiles import TileFanOut, cancel_tiles, remove_tile_inputs
from app.kit.allocator import release_freed_memory_promptly
from app.kit.scan_files import stored_bag_options, with_stored_trajectory

if TYPE_CHECKING:  # not imported: the API process imports this package, not the pipeline
    from app.core.comparison.protocol import Comparison

logger = logging.getLogger("scandiff.jobs")


API_FIXES_OF_ERRORS = {
    "skip_alignment": ' ("align": false in the job\'s params: POST /api/v1/jobs/{job_id}/rerun)',
    "free_disk": " (ask the operator: the data directory's disk, SCANDIFF_MIN_FREE_DISK_BYTES)",
}
"""The API's knob for each ``how_to_fix`` a core error names (a job's error is read over HTTP)."""


def api_error_message(exc: InputError) -> str:
    """A core input error as a job's ``error``: its message, with the API's knob for the fix."""
    return str(exc) + API_FIXES_OF_ERRORS.get(getattr(exc, "how_to_fix", None) or "", "")


def compute(
    job: ClaimedJob, settings: Settings, keeper: LeaseKeeper
) -> tuple[Comparison, dict[str, float]]:
    """Read both scans and run ``compare``; the result and this job's own timings."""
    release_freed_memory_promptly()  # freed temporaries go back to the system: peak = live data
    job_hooks.inject_faults(job, keeper)
    compare = job_hooks.comparison()
    if job.storage_problem is not None:
        raise InputError(job.storage_problem)
    if job.reference_path is None or job.scan_path is None:
        raise InputError("the job's reference scan or scan no longer exists")
    keeper.report("loading", 0.0)
    started, started_cpu = time.perf_counter(), time.process_time()
    threads = job_threads(settings)  # the result does not depend on it
    if job_hooks.compare is None and streamed_tiles(job, settings):
        return streamed_compute(job, settings, keeper, threads)
    reference = read_point_cloud(
        job.reference_path,
        format=job.reference_format,
        threads=threads,
        bag_options=stored_bag_options(job.reference_path),  # the upload's, for a ROS bag
    )
    scan = read_point_cloud(
        job.scan_path,
        format=job.scan_format,
        threads=threads,
        bag_options=stored_bag_options(job.scan_path),
    )
    reference = with_stored_trajectory(reference, job.reference_path)  # if one was given
    scan = with_stored_trajectory(scan, job.scan_path)
    given_at_upload = {
        "reference": given_at_upload_only(reference.sensor_origin, job.reference_sensor_origin),
        "scan": given_at_upload_only(scan.sensor_origin, job.scan_sensor_origin),
    }
    # The origin given at upload wins over the file's; a job's params override both.
    if job.reference_sensor_origin is not None:
        reference = dataclasses.replace(
            reference, sensor_origin=np.asarray(job.reference_sensor_origin, dtype=np.float64)
        )
    if job.scan_sensor_origin is not None:
        scan = dataclasses.replace(
            scan, sensor_origin=np.asarray(job.scan_sensor_origin, dtype=np.float64)
        )
    job_timings = {
        "load_inputs": time.perf_counter() - started,
        "load_inputs_cpu": time.process_time() - started_cpu,
    }
    keeper.report("comparing", PROGRESS_LOADED)
    cache = geometry_cache_of(job)
    options: dict[str, Any] = {}
    fan_out: TileFanOut | None = None
    if job_hooks.compare is None:  # the real comparison, within the worker's memory budget
        if tiles_needed(settings, len(reference), len(scan)):
            fan_out = TileFanOut(job, settings, keeper)  # tiles on every worker
            compare, cache = tiled_comparison(fan_out, settings), None
        else:
            options["budget_bytes"] = settings.worker_memory_budget_bytes
    result = compare(
        reference,
        scan,
        **options,
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
    job_timings["compute_cpu"] = time.process_time() - started_cpu  # this process only
    if fan_out is not None:
        job_timings.update(fan_out.timings.seconds)
    return label_upload_origins(result, given_at_upload), job_timings


def streamed_tiles(job: ClaimedJob, settings: Settings) -> bool:
    """Whether a job is compared streamed (:mod:`app.core.tiling.streamed`): tiled, and both
    files carry coordinates only (no origin given at upload, no trajectory or bag beside them).
    """
    from app.core.formats.streamed import declared_rows  # the worker's imports, not the API's
    from app.core.tiling.pair_files import coordinates_only
    from app.kit.scan_files import bag_options_path, trajectory_path

    paths = [job.reference_path, job.scan_path]
    if None in paths or job.storage_problem is not None:
        return False
    if job.reference_sensor_origin is not None or job.scan_sensor_origin is not None:
        return False
    formats = [job.reference_format, job.scan_format]
    for path, format in zip(paths, formats, strict=True):
        if trajectory_path(path).exists() or bag_options_path(path).exists():
            return False
        if not coordinates_only(path, format):
            return False
    rows = [declared_rows(path, format) for path, format in zip(paths, formats, strict=True)]
    return None not in rows and tiles_needed(settings, *rows)  # type: ignore[arg-type]


def streamed_compute(
    job: ClaimedJob, settings: Settings, keeper: LeaseKeeper, threads: int
) -> tuple[Comparison, dict[str, float]]:
    """:func:`compute` of a job whose files are read in chunks: the tiles' inputs written
    from them (one crop pass a file on the queue), the tiles on the queue, the labels merged
    into files (this worker never holds the whole pair)."""
    from app.core.tiling.streamed import compare_streamed

    started, started_cpu = time.perf_counter(), time.process_time()
    fan_out = TileFanOut(job, settings, keeper)
    crop_fan_out = CropPassFanOut(job, settings, keeper, fan_out.timings)
    keeper.report("comparing", PROGRESS_LOADED)
    result = compare_streamed(
        job.reference_path,  # type: ignore[arg-type]  # checked by streamed_tiles
        job.scan_path,  # type: ignore[arg-type]
        budget_bytes=settings.worker_memory_budget_bytes or DEFAULT_MEMORY_BUDGET_BYTES,
        work_dir=settings.data_layout.job_tiles_dir(job.id),
        formats=(job.reference_format, job.scan_format),
        max_crop_points=settings.tile_crop_points,
        run_tiles=fan_out,
        run_crops=crop_fan_out,
        keep_free_disk_bytes=settings.min_free_disk_bytes,
        free_disk=job_hooks.free_disk,
        method=job.method,
        variant=job.variant,
        params=job.params,
        progress=keeper.compare_progress,
        threads=threads,
        site_calibration=job.site_calibration,
    )
    job_timings = {
        "load_inputs": 0.0,
        "load_inputs_cpu": 0.0,
        "compute_cpu": time.process_time() - started_cpu,
        "streamed_seconds": time.perf_counter() - started,
        **fan_out.timings.seconds,
    }
    return result, job_timings


def tiles_needed(settings: Settings, n_reference: int, n_scan: int) -> bool:
    """Whether a pair is compared tile by tile: forced, or too large for the memory budget."""
    from app.core.tiling.compare import fits_budget  # the worker's import, not the API's

    budget = settings.worker_memory_budget_bytes
    return bool(settings.tile_crop_points) or (
        budget is not None and not fits_budget(n_reference, n_scan, budget)
    )


def tiled_comparison(fan_out: TileFanOut, settings: Settings) -> Callable[..., Any]:
    """``compare`` for a pair compared in tiles that every worker takes from the queue."""
    from app.core.tiling.compare import compare_tiled

    budget = settings.worker_memory_budget_bytes or DEFAULT_MEMORY_BUDGET_BYTES

    def compare(*clouds: Any, geometry_cache: Any = None, **options: Any) -> Any:
        return compare_tiled(
            *clouds,
            budget_bytes=budget,
            max_crop_points=settings.tile_crop_points,
            run_tiles=fan_out,
            **options,
        )

    return compare


def given_at_upload_only(
    from_file: np.ndarray | None, stored: list[float] | list[list[float]] | None
) -> bool:
    """Whether a scan's stored origin was given at upload (the file has none, or another)."""
    if stored is None:
        return False
    given = np.asarray(stored, dtype=np.float64)
    return (
        from_file is None
        or np.shape(from_file) != given.shape
        or not np.allclose(from_file, given, rtol=0.0, atol=1e-9)
    )


def label_upload_origins(result: Comparison, given_at_upload: dict[str, bool]) -> Comparison:
    """``result`` with the origins given at upload reported as ``"given"``, not ``"file"``.

    The worker hands a scan's upload origin to ``compare`` in the file's slot (it overrides the
    file's own); the report names where it came from: ``sensor_origins[side][i].source``,
    ``visibility[side].origins`` (also in ``calibration.visibility``) and the warnings.
    """
    sides = [side for side, given in given_at_upload.items() if given]
    if not sides:
        return result
    sensor_origins = {
        side: [
            dataclasses.replace(entry, source="given")
            if side in sides and entry.source == "file"
            else entry
            for entry in entries
        ]
        for side, entries in result.sensor_origins.items()
    }
    visibility = {
        side: dataclasses.replace(seen, origins="given")
        if side in sides and seen.origins == "file"
        else seen
        for side, seen in result.visibility.items()
    }
    warnings = list(result.warnings)
    for side in sides:
        warnings = [
            warning.replace(f"the {side}'s file sensor origin", f"the {side}'s given sensor origin")
            for warning in warnings
        ]
    return dataclasses.replace(  # type: ignore[type-var]  # a dataclass: warnings recomputed
        result,
        sensor_origins=sensor_origins,
        visibility=visibility,
        warnings=warnings,
        calibration=dataclasses.replace(result.calibration, visibility=visibility),
    )


def execute_job(job_id: str, settings: Settings) -> JobOutcome:
    """Run job ``job_id`` once if it needs running; the outcome.

    Outcomes: ``succeeded``, ``failed``, ``queued`` (to be retried: the caller sends its message
    again), ``skipped`` (duplicate message, finished or leased elsewhere), ``lease-lost`` (taken
    over; nothing written).
    """
    owner = make_lease_owner()
    job = claim_job(job_id, settings, owner)
    if job is None:
        return JobOutcome.SKIPPED
    keeper = LeaseKeeper(job, settings).start()
    started = time.perf_counter()
    limit_bytes = job_memory_limit(settings)
    try:
        with memory_limit(limit_bytes):
            result, job_timings = compute(job, settings, keeper)
            keeper.report("writing", PROGRESS_COMPARED)
            write_started, write_cpu = time.perf_counter(), time.process_time()
            labels_path = write_result_files(job, settings, result)
            job_timings["write_outputs"] = time.perf_counter() - write_started
            job_timings["write_outputs_cpu"] = time.process_time() - write_cpu
        keeper.report("storing", PROGRESS_COMPARED)
        keeper.stop()
        keeper.check()
        job_timings["job_total"] = time.perf_counter() - started
        timings = {**dict(result.timings), **job_timings}
        if not store_results(job, settings, result, labels_path, timings):
            job_log("job lease lost before storing; nothing stored", job.id, JobOutcome.LEASE_LOST)
            return JobOutcome.LEASE_LOST
        remove_tile_inputs(settings, job.id)  # the merged labels are stored; tiles no longer read
        job_log(
            "job succeeded",
            job.id,
            JobOutcome.SUCCEEDED,
            attempt=job.attempt,
            seconds=round(job_timings["job_total"], 3),
            n_regions=len(result.regions),
            changed=bool(result.changed),
        )
        return JobOutcome.SUCCEEDED
    except LeaseLostError:
        job_log(
            "job lease lost; nothing stored", job.id, JobOutcome.LEASE_LOST, attempt=job.attempt
        )
        return JobOutcome.LEASE_LOST
    except InputError as exc:
        keeper.stop()
        if not fail_job(job, settings, api_error_message(exc)):
            return JobOutcome.LEASE_LOST
        cancel_tiles(settings, job.id)
        return JobOutcome.FAILED
    except MemoryError:
        keeper.stop()
        message = (
            f"out of memory: the job needs more than the worker's memory cap "
            f"(SCANDIFF_JOB_MEMORY_LIMIT_BYTES={limit_bytes})"
            if limit_bytes
            else "out of memory"
        )
        if not fail_job(job, settings, message):
            return JobOutcome.LEASE_LOST
        cancel_tiles(settings, job.id)
        return JobOutcome.FAILED
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
