"""Per-point results of a job as files: the worker's ``labels.npz``, or PLY/LAS of both clouds.

``npz`` is the worker's file as written (exactly the arrays of ``scandiff compare --labels``:
``reference_changed, scan_changed, reference_label, scan_label``, one entry per source row).
``ply``/``las`` hold the finite points of both clouds in the reference's file frame (the scan
moved by the job's registration) with the per-point fields of ``scandiff compare --export``
(:func:`app.core.pair_export.both_clouds`): ``cloud`` (0 reference, 1 scan), ``label`` (1
changed, 0 unchanged, -1 unobserved), ``distance`` (NaN where unknown) and ``region`` (the
region's index, -1: none or a job from before regions were kept per point).  They
are built on first request, outside any transaction, and kept next to the labels.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy.orm import Session

from app.config import Settings
from app.core.pair_export import both_clouds
from app.core.registration import apply_transform
from app.db.models import JobStatus, new_id
from app.jobs.results import read_result_files
from app.services import jobs, scans, storage
from app.services.auth import Principal
from app.services.errors import ConflictError, NotFoundError
from app.services.scans import PARSE_SLOTS, DownloadFile
from app.services.transaction import end_read_transaction


@dataclass(frozen=True)
class CloudSource:
    """A stored scan file to read."""

    path: Path
    format: str
    filename: str


def _cloud_in_file_order(
    cloud_source: CloudSource, labels: np.ndarray, max_points: int
) -> tuple[np.ndarray, Callable[[np.ndarray | None], np.ndarray | None]]:
    """The cloud's points and a function putting a per-source-row array in their order."""
    from app.core.formats import read_point_cloud
    from app.kit.scan_files import stored_bag_options

    cloud = read_point_cloud(
        cloud_source.path,
        cloud_source.format,
        filename=cloud_source.filename,
        max_points=max_points,
        bag_options=stored_bag_options(cloud_source.path),  # a bag reads as its job read it
    )
    if labels.shape != (cloud.n_source,):
        raise ConflictError(
            f"the job's labels have {labels.shape[0]} entries but {cloud_source.filename} has "
            f"{cloud.n_source} points; the stored results do not match the scan"
        )

    def in_point_order(values: np.ndarray | None) -> np.ndarray | None:
        if values is None or values.shape != (cloud.n_source,):
            return None  # older results: the export fills in NaN / -1
        return cloud.from_source_order(values)

    return cloud.points, in_point_order


def _scan_to_reference_frame(points: np.ndarray, registration: dict[str, Any] | None) -> np.ndarray:
    transform = np.asarray((registration or {}).get("transform", np.eye(4)), dtype=np.float64)
    if transform.shape != (4, 4) or not np.isfinite(transform).all():
        return points
    return apply_transform(points, transform)


def build_labels_cloud(
    target: Path,
    file_format: str,
    labels_path: Path,
    reference: CloudSource,
    scan: CloudSource,
    registration: dict[str, Any] | None,
    settings: Settings,
) -> None:
    """Write both clouds with ``cloud``, ``label``, ``distance`` and ``region`` to ``target``."""
    from app.core.formats import write_point_cloud

    with PARSE_SLOTS:
        stored = read_result_files(labels_path)
        reference_points, reference_order = _cloud_in_file_order(
            reference, stored.reference_label, settings.max_points
        )
        scan_points, scan_order = _cloud_in_file_order(scan, stored.scan_label, settings.max_points)
        points, fields = both_clouds(
            reference_points,
            _scan_to_reference_frame(scan_points, registration),
            labels=(reference_order(stored.reference_label), scan_order(stored.scan_label)),
            distances=(
                reference_order(stored.reference_distance),
                scan_order(stored.scan_distance),
            ),
            regions=(reference_order(stored.reference_region), scan_order(stored.scan_region)),
        )
        temporary = target.parent / f".{target.name}.{os.getpid()}-{new_id()}.tmp"
        try:
            write_point_cloud(temporary, points, fields, format=file_format)
            storage.install_file(temporary, target)
        finally:
            storage.remove_file(temporary)


def labels_file(
    session: Session, settings: Settings, principal: Principal, job_id: str, file_format: str
) -> DownloadFile:
    """The per-point labels of a succeeded job as ``npz``, ``ply`` or ``las``."""
    job = jobs.get_job(session, principal, job_id)
    if job.status != JobStatus.SUCCEEDED or not job.labels_path:
        raise ConflictError(
            f"job {job.id} is {job.status}; its labels exist once it has succeeded",
            code="job_not_succeeded",
        )
    labels_path = storage.stored_file(settings, job.labels_path)
    if not labels_path.is_file():
        raise NotFoundError(f"the labels of job {job.id} are missing from storage")
    download_name = f"{job.id}-labels.{file_format}"
    if file_format == "npz":
        end_read_transaction(session)
        return DownloadFile(path=labels_path, filename=download_name)
    reference_scan = scans.get_scan(session, principal, job.reference_scan_id)
    scan = scans.get_scan(session, principal, job.scan_id)
    reference = CloudSource(
        path=storage.stored_file(settings, reference_scan.storage_path),
        format=reference_scan.format,
        filename=reference_scan.filename,
    )
    compared = CloudSource(
        path=storage.stored_file(settings, scan.storage_path),
        format=scan.format,
        filename=scan.filename,
    )
    registration = dict(job.registration or {})
    end_read_transaction(session)
    target = labels_path.parent / f"labels.{file_format}"
    if not target.is_file():
        build_labels_cloud(
            target, file_format, labels_path, reference, compared, registration, settings
        )
    return DownloadFile(path=target, filename=download_name)
