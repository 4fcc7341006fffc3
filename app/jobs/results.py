"""A job's results: the per-point files under ``results/<job_id>/`` and the row, stored once.

:func:`write_result_files` writes ``labels.npz`` (the arrays of ``scandiff compare --labels``)
and ``details.npz`` (``reference_distance``, ``scan_distance``, float32, and
``reference_region``, ``scan_region``, int32, -1 outside every region; source order), each
atomically (:func:`app.core.files.write_atomically`); :func:`read_result_files` reads them
back (the labels downloads, the 3D view).  :func:`store_results` stores score, decision,
regions, registration, timings and the job's event in **one short transaction**, only if the
worker still holds the job's lease.  :func:`remove_stale_temp_files` deletes what a worker
killed while writing left.
"""

from __future__ import annotations

import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from sqlalchemy import delete, select

from app.clock import utc_now
from app.config import Settings
from app.core.files import TEMP_MARKER, write_atomically
from app.core.jsonable import json_safe
from app.db.models import Job, JobStatus, Region
from app.db.session import transaction
from app.jobs.alerts.events import publish_job_finished
from app.jobs.alerts.site_history import region_count_warning
from app.jobs.leases import ClaimedJob, held_by
from app.kit.data_layout import DETAILS_FILENAME, LABELS_FILENAME

if TYPE_CHECKING:  # not imported: the API process imports this package, not the pipeline
    from app.core.comparison.protocol import Comparison


@dataclass(frozen=True)
class StoredResults:
    """A job's per-point results read back, one entry per source row of each file.

    ``*_distance`` are None for jobs from before ``details.npz``; ``*_region`` for jobs from
    before it held the region indices.
    """

    reference_label: NDArray[np.int8]
    scan_label: NDArray[np.int8]
    reference_distance: NDArray[np.float32] | None
    scan_distance: NDArray[np.float32] | None
    reference_region: NDArray[np.int32] | None
    scan_region: NDArray[np.int32] | None


def read_labels(labels_path: Path) -> tuple[NDArray[np.int8], NDArray[np.int8]]:
    """The reference's and the scan's labels stored at ``labels_path`` (int8, one per file row)."""
    with np.load(labels_path) as labels:
        return (
            np.asarray(labels["reference_label"], dtype=np.int8),
            np.asarray(labels["scan_label"], dtype=np.int8),
        )


def read_result_files(labels_path: Path) -> StoredResults:
    """The labels at ``labels_path`` and the distances and regions beside them, if any."""
    reference_label, scan_label = read_labels(labels_path)
    details: dict[str, NDArray] = {}
    details_path = labels_path.with_name(DETAILS_FILENAME)
    if details_path.is_file():
        with np.load(details_path) as stored:
            details = {name: np.asarray(stored[name]) for name in stored.files}
    return StoredResults(
        reference_label=reference_label,
        scan_label=scan_label,
        reference_distance=details.get("reference_distance"),
        scan_distance=details.get("scan_distance"),
        reference_region=details.get("reference_region"),
        scan_region=details.get("scan_region"),
    )


def write_result_files(job: ClaimedJob, settings: Settings, result: Comparison) -> str:
    """Write ``labels.npz`` and ``details.npz`` atomically; the labels path relative to data_dir."""
    directory = settings.data_layout.job_results_dir(job.id)
    labels_path = directory / LABELS_FILENAME
    if isinstance(result.reference_label, np.memmap):  # a streamed comparison's, on disk
        from app.core.tiling.pair_files import (
            streamed_outputs,
            write_details_npz,
            write_labels_npz,
        )

        outputs = streamed_outputs(result)  # type: ignore[arg-type]
        if outputs is not None:  # copied from its files: never the whole clouds in memory
            write_atomically(labels_path, lambda path: write_labels_npz(path, outputs))
            write_atomically(
                directory / DETAILS_FILENAME, lambda path: write_details_npz(path, outputs)
            )
            return settings.data_layout.stored_form(labels_path)
    write_atomically(labels_path, result.write_labels_npz)
    write_atomically(
        directory / DETAILS_FILENAME,
        lambda path: np.savez(
            path,
            reference_distance=np.asarray(result.reference_distance, dtype=np.float32),
            scan_distance=np.asarray(result.scan_distance, dtype=np.float32),
            reference_region=np.asarray(result.reference_region, dtype=np.int32),
            scan_region=np.asarray(result.scan_region, dtype=np.int32),
        ),
    )
    return settings.data_layout.stored_form(labels_path)


def store_results(
    job: ClaimedJob,
    settings: Settings,
    result: Comparison,
    labels_path: str,
    timings: dict[str, float],
) -> bool:
    """One short transaction: results and Region rows, only if the lease is still ours.

    With them: the sensor origins used, the quality warnings (the core's, and a region count
    far above the site's history) and the explanation of the decision.
    """
    with transaction(settings.sqlalchemy_url) as session:
        row = session.execute(
            select(Job).where(held_by(job.id, job.lease_owner)).with_for_update()
        ).scalar_one_or_none()
        if row is None:
            return False
        session.execute(delete(Region).where(Region.job_id == job.id))
        session.add_all(
            Region(
                job_id=job.id,
                ordinal=ordinal,
                kind=str(region.kind),
                n_points=int(region.n_points),
                centroid=json_safe(list(region.centroid)),
                bbox_min=json_safe(list(region.bbox_min)),
                bbox_max=json_safe(list(region.bbox_max)),
                mean_distance=float(region.mean_distance),
                max_distance=float(region.max_distance),
                evidence=str(region.evidence),
                confidence=region.confidence,
            )
            for ordinal, region in enumerate(result.regions)
        )
        row.status = JobStatus.SUCCEEDED
        row.score = float(result.score)
        row.threshold = float(result.threshold)
        row.changed = bool(result.changed)
        row.calibration = json_safe(result.calibration.to_json_dict())
        row.effective_params = json_safe(result.params)
        row.registration = json_safe(result.registration.to_json_dict())
        row.n_regions = len(result.regions)
        warnings = [warning.to_json_dict() for warning in result.quality_warnings]
        history_warning = region_count_warning(session, row, len(result.regions))
        if history_warning is not None:
            warnings.append(history_warning.to_json_dict())
        row.warnings = json_safe(warnings)
        row.explanation = json_safe(result.explanation.to_json_dict())
        row.sensor_origins = json_safe(result.sensor_origins_json())
        row.uncertain_regions = json_safe(
            [region.to_json_dict() for region in result.uncertain_regions]
        )
        row.timings = json_safe(timings)
        row.labels_path = labels_path
        row.error = None
        row.progress = 1.0
        row.stage = "succeeded"
        row.finished_at = utc_now()
        row.lease_expires_at = None
        publish_job_finished(session, job.id)  # job.changed / job.unchanged, same transaction
    return True


def remove_stale_temp_files(settings: Settings, older_than_seconds: float) -> int:
    """Delete temporary result files older than ``older_than_seconds``; how many."""
    if not settings.results_dir.is_dir():
        return 0
    cutoff = time.time() - older_than_seconds
    removed = 0
    for path in settings.results_dir.glob(f"*/.*{TEMP_MARKER}*"):
        try:
            if path.stat().st_mtime <= cutoff:
                path.unlink()
                removed += 1
        except FileNotFoundError:
            continue
    return removed


def remove_finished_tile_inputs(settings: Settings) -> int:
    """Delete the tile inputs of jobs that no longer run (finished, failed or deleted); how many.

    A job removes its own once its labels are stored, but a worker killed between the two, or a
    failed job, leaves them: a 100M-point pair's crops are tens of GB.  A queued or running job
    keeps its tiles (a finished tile is never computed again).
    """
    if not settings.results_dir.is_dir():
        return 0
    tile_dirs = {path.parent.name: path for path in settings.results_dir.glob("*/tiles")}
    if not tile_dirs:
        return 0
    with transaction(settings.sqlalchemy_url) as session:
        unfinished = set(
            session.scalars(
                select(Job.id).where(
                    Job.id.in_(list(tile_dirs)), Job.status.in_(JobStatus.unfinished())
                )
            )
        )
    removed = 0
    for job_id, directory in tile_dirs.items():
        if job_id not in unfinished:
            shutil.rmtree(directory, ignore_errors=True)
            removed += not directory.exists()
    return removed
