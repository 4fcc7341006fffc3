"""Load a finished job's scene from the database and the data directory.

Reads the job row (registration transform, decision), its regions, both scan files (with the
core's readers) and the per-point labels the worker wrote to ``results_dir/<job_id>/labels.npz``;
returns the :class:`~app.viewer.scene.SceneData` the 3D view draws. Clouds larger than the
``viewer_stream_above_points`` setting are not loaded whole: only the points drawn are read
(:mod:`app.viewer.large_scene`), and :func:`load_job_box` reads a box at full density.
Authorisation is the caller's business (the viewer's routes ask their authoriser first).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.config import Settings
from app.core.formats import read_point_cloud
from app.db.models import Job, JobStatus, Scan, Site
from app.db.session import session_factory
from app.jobs.results import read_result_files
from app.kit.data_layout import DETAILS_FILENAME
from app.kit.scan_files import stored_bag_options
from app.services.schemas import RegionRead
from app.viewer.large_scene import SceneContext, StoredSide, box_scene, budget_scene
from app.viewer.scene import DEFAULT_POINT_BUDGET, SceneData, build_scene_data
from app.viewer.scene_parts import SIDES
from app.viewer.stored_results import stored_distances, stored_labels


def job_sensor_origins(job: Any) -> dict[str, Any]:
    """The sensor positions the job reports, ``{"reference": [...], "scan": [...]}`` (jobs
    stored before migration 0008 have none)."""
    value = job.sensor_origins or {}
    return value if isinstance(value, dict) else {}


def job_warnings(job: Any) -> list[dict[str, Any]]:
    """The job's quality warnings, a list of ``{code, message, ...}`` (none before 0008)."""
    value = job.warnings or []
    return [item for item in value if isinstance(item, dict)] if isinstance(value, list) else []


def job_uncertain_regions(job: Any) -> list[dict[str, Any]]:
    """The places the job's other epoch never covered, ``[{kind, n_points, bbox_min, ...}]``
    (evidence ``no_coverage``; jobs stored before migration 0010 have none)."""
    value = getattr(job, "uncertain_regions", None) or []
    return [
        {**item, "evidence": item.get("evidence") or "no_coverage"}
        for item in (value if isinstance(value, list) else [])
        if _is_region(item)
    ]


def _is_region(item: Any) -> bool:
    """Whether ``item`` is a region the view can draw: a kind, a point count, a finite box."""
    if not isinstance(item, dict) or not isinstance(item.get("n_points"), int):
        return False
    try:
        corners = np.asarray([item["bbox_min"], item["bbox_max"]], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        return False
    return corners.shape == (2, 3) and bool(np.isfinite(corners).all()) and "kind" in item


def job_min_region_points(job: Any) -> int | None:
    """The minimum region size the job asked for, if it set one."""
    params = getattr(job, "effective_params", None) or {}
    localisation = params.get("localisation") if isinstance(params, dict) else None
    value = localisation.get("min_region_points") if isinstance(localisation, dict) else None
    return int(value) if isinstance(value, int | float) and value >= 1 else None


class ViewUnavailableError(Exception):
    """The job cannot be shown (yet); ``status`` is the HTTP status to answer with."""

    def __init__(self, message: str, status: int = 409) -> None:
        super().__init__(message)
        self.message = message
        self.status = status


def job_labels_path(settings: Settings, job: Job) -> Path:
    """Where the worker wrote the job's per-point labels."""
    default = settings.data_layout.labels_file(job.id)
    if job.labels_path and not default.exists():
        return settings.data_layout.resolve(job.labels_path)
    return default


def job_view_problem(settings: Settings, job_id: str) -> ViewUnavailableError | None:
    """Why the job's view cannot open (no such job, failed, not finished yet), or None."""
    with session_factory(settings.sqlalchemy_url, read_only=True)() as session:
        job = session.get(Job, job_id)
        if job is None:
            return ViewUnavailableError(f"job {job_id} not found", status=404)
        if job.status == JobStatus.FAILED:
            return ViewUnavailableError(
                f"job {job_id} failed: {job.error or 'no reason recorded'}", status=409
            )
        if job.status != JobStatus.SUCCEEDED:
            return ViewUnavailableError(
                f"job {job_id} is still {job.status} ({job.progress:.0%}); the 3D view opens "
                "once it has finished",
                status=409,
            )
        return None


@dataclass(frozen=True)
class StoredJob:
    """What the view of a succeeded job reads: its files and what the API says of it."""

    paths: tuple[Path, Path]
    names: tuple[str, str]
    labels_path: Path
    context: SceneContext

    @property
    def details_path(self) -> Path:
        """The per-point distances beside the labels (jobs before details.npz have none)."""
        return self.labels_path.with_name(DETAILS_FILENAME)

    @property
    def title(self) -> str:
        """``site: scan vs reference``."""
        site_name = (self.context.summary or {}).get("site") or "site"
        return f"{site_name}: {self.names[1]} vs {self.names[0]}"


def stored_job(settings: Settings, job_id: str) -> StoredJob:
    """The files and facts of a succeeded job.

    Raises
    ------
    ViewUnavailableError
        The job does not exist (404), has not succeeded (409) or its files are missing (410).
    """
    session = session_factory(settings.sqlalchemy_url)()
    try:
        job = session.get(Job, job_id)
        if job is None:
            raise ViewUnavailableError(f"job {job_id} not found", status=404)
        if job.status != JobStatus.SUCCEEDED:
            reason = f": {job.error}" if job.status == JobStatus.FAILED and job.error else ""
            raise ViewUnavailableError(
                f"job {job_id} is {job.status}{reason}; the 3D view opens once it has succeeded"
            )
        reference = session.get(Scan, job.reference_scan_id)
        scan = session.get(Scan, job.scan_id)
        site = session.get(Site, job.site_id)
        if reference is None or scan is None:
            raise ViewUnavailableError(f"the scans of job {job_id} were deleted", status=410)
        transform = (job.registration or {}).get("transform")
        stored = StoredJob(
            paths=(
                settings.data_layout.resolve(reference.storage_path),
                settings.data_layout.resolve(scan.storage_path),
            ),
            names=(reference.filename, scan.filename),
            labels_path=job_labels_path(settings, job),
            context=SceneContext(
                transform=np.eye(4) if transform is None else np.asarray(transform, np.float64),
                regions=[RegionRead.from_model(region).model_dump() for region in job.regions],
                uncertain_regions=job_uncertain_regions(job),
                summary={
                    "score": job.score,
                    "threshold": job.threshold,
                    "changed": job.changed,
                    "n_regions": job.n_regions,
                    "site": site.name if site else None,
                    "method": job.method,
                    "variant": job.variant,
                },
                sensor_origins=job_sensor_origins(job),
                warnings=job_warnings(job),
                min_region_points=job_min_region_points(job),
            ),
        )
    finally:
        session.close()
    for path in (*stored.paths, stored.labels_path):
        if not path.is_file():
            raise ViewUnavailableError(
                f"a file of job {job_id} is missing from the data directory ({path.name})",
                status=410,
            )
    return stored


def load_job_scene(
    settings: Settings,
    job_id: str,
    *,
    point_budget: int = DEFAULT_POINT_BUDGET,
    stream_above_points: int | None = None,
) -> tuple[SceneData, str]:
    """The scene of a succeeded job and a title for it.

    Clouds of more than ``stream_above_points`` points (default: the
    ``viewer_stream_above_points`` setting) are not loaded: the points drawn are read from
    the files (:func:`~app.viewer.large_scene.budget_scene`).

    Raises
    ------
    ViewUnavailableError
        The job does not exist (404), has not succeeded (409) or its files are missing (410).
    """
    job = stored_job(settings, job_id)
    labels = stored_labels(job.labels_path)
    limit = stream_above_points
    if limit is None:
        limit = settings.viewer_stream_above_points
    if max(len(values) for values in labels.values()) > limit:
        return budget_scene(_stored_sides(job, labels), job.context, point_budget), job.title
    reference_cloud = read_point_cloud(job.paths[0], bag_options=stored_bag_options(job.paths[0]))
    scan_cloud = read_point_cloud(job.paths[1], bag_options=stored_bag_options(job.paths[1]))
    stored = read_result_files(job.labels_path)
    reference_labels = reference_cloud.from_source_order(stored.reference_label)
    scan_labels = scan_cloud.from_source_order(stored.scan_label)
    distances: dict[str, Any] = {}
    if stored.reference_distance is not None and stored.scan_distance is not None:
        distances = {  # jobs from before details.npz have labels only
            "reference_distances": reference_cloud.from_source_order(stored.reference_distance),
            "scan_distances": scan_cloud.from_source_order(stored.scan_distance),
        }
    context = job.context
    data = build_scene_data(
        reference_cloud.points,
        scan_cloud.points,
        reference_labels=reference_labels,
        scan_labels=scan_labels,
        transform=context.transform,
        regions=context.regions,
        uncertain_regions=context.uncertain_regions,
        point_budget=point_budget,
        summary=context.summary,
        sensor_origins=context.sensor_origins,
        warnings=context.warnings,
        min_region_points=context.min_region_points,
        **distances,
    )
    return data, job.title


def load_job_box(
    settings: Settings,
    job_id: str,
    low: Sequence[float],
    high: Sequence[float],
    *,
    point_budget: int = DEFAULT_POINT_BUDGET,
    origin: NDArray[np.float64] | None = None,
) -> SceneData:
    """The job's points inside a box (reference frame, file coordinates) at full density, up
    to ``point_budget`` (:func:`~app.viewer.large_scene.box_scene`; a warning says when the
    box holds more); ``origin``: the local origin of the view it replaces.

    Raises
    ------
    ViewUnavailableError
        As :func:`load_job_scene`; a malformed box (422).
    """
    job = stored_job(settings, job_id)
    sides = _stored_sides(job, stored_labels(job.labels_path))
    try:
        return box_scene(sides, job.context, low, high, point_budget, origin)
    except ValueError as exc:
        raise ViewUnavailableError(str(exc), status=422) from exc


def _stored_sides(job: StoredJob, labels: dict[str, NDArray[np.int8]]) -> dict[str, StoredSide]:
    """Both scans of ``job`` as :class:`~app.viewer.large_scene.StoredSide`."""
    distances = stored_distances(
        job.details_path, {side: len(values) for side, values in labels.items()}
    )
    return {
        side: StoredSide(path, labels[side], distances[side], stored_bag_options(path))
        for side, path in zip(SIDES, job.paths, strict=True)
    }
