"""A job's results: the per-point files under ``results/<job_id>/`` and the row, stored once.

:func:`write_result_files` writes ``labels.npz`` (the arrays of ``scandiff compare --labels``)
and ``details.npz`` (``reference_distance``, ``scan_distance``, float32, source order), each
atomically (:func:`app.core.files.write_atomically`).  :func:`store_results` stores score, decision,
regions, registration, timings and the job's event in **one short transaction**, only if the
worker still holds the job's lease.  :func:`remove_stale_temp_files` deletes what a worker
killed while writing left.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy import delete, select

from app.clock import utc_now
from app.config import Settings
from app.core.explanation import explain_comparison
from app.core.files import TEMP_MARKER, write_atomically
from app.core.jsonable import json_safe
from app.core.quality import quality_warnings
from app.db.models import Job, JobStatus, Region
from app.db.session import transaction
from app.jobs.alerts import publish_job_finished
from app.jobs.leases import ClaimedJob, held_by
from app.jobs.site_history import region_count_warning

LABELS_FILENAME = "labels.npz"
DETAILS_FILENAME = "details.npz"


def job_results_dir(settings: Settings, job_id: str) -> Path:
    """Where the per-point files of job ``job_id`` live."""
    return settings.results_dir / job_id


def write_result_files(job: ClaimedJob, settings: Settings, result: Any) -> str:
    """Write ``labels.npz`` and ``details.npz`` atomically; the labels path relative to data_dir."""
    directory = job_results_dir(settings, job.id)
    labels_path = directory / LABELS_FILENAME
    write_atomically(labels_path, result.write_labels_npz)
    write_atomically(
        directory / DETAILS_FILENAME,
        lambda path: np.savez(
            path,
            reference_distance=np.asarray(result.reference_distance, dtype=np.float32),
            scan_distance=np.asarray(result.scan_distance, dtype=np.float32),
        ),
    )
    return labels_path.relative_to(settings.data_dir).as_posix()


def store_results(
    job: ClaimedJob, settings: Settings, result: Any, labels_path: str, timings: dict[str, float]
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
                evidence=str(getattr(region, "evidence", "seen_empty")),
                confidence=getattr(region, "confidence", None),
            )
            for ordinal, region in enumerate(result.regions)
        )
        row.status = JobStatus.SUCCEEDED
        row.score = float(result.score)
        row.threshold = float(result.threshold)
        row.changed = bool(result.changed)
        row.calibration = json_safe(result.calibration)
        row.effective_params = json_safe(getattr(result, "params", None))
        row.registration = json_safe(result.registration)
        row.n_regions = len(result.regions)
        warnings = quality_warnings(result)
        history_warning = region_count_warning(session, row, len(result.regions))
        row.warnings = json_safe(warnings + ([history_warning] if history_warning else []))
        row.explanation = json_safe(explain_comparison(result))
        row.sensor_origins = json_safe(getattr(result, "sensor_origins", None))
        row.uncertain_regions = json_safe(
            [region.to_json_dict() for region in getattr(result, "uncertain_regions", [])]
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
