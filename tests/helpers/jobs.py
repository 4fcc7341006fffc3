"""Job rows for tests: create them with their scans on disk, read them, play the worker."""

from __future__ import annotations

import dataclasses
import os
import time
from typing import Any

import numpy as np
from numpy.typing import NDArray
from sqlalchemy import func, select

from app.config import Settings
from app.core.pipeline import ComparisonResult, RegionSummary
from app.db.models import Job, Organisation, Region, Scan, Site
from app.db.session import transaction
from app.jobs.leases import claim_job, make_lease_owner
from app.jobs.results import store_results, write_result_files
from app.testing.results import calibration_report, registration_report
from app.testing.scenes import corridor_points
from tests.helpers.job_rows import new_job
from tests.helpers.server import ApiServer

FAST_LEASES = {
    "job_lease_seconds": 2.0,
    "job_heartbeat_seconds": 0.25,
    "recovery_interval_seconds": 0.5,
    "job_max_attempts": 3,
}
"""Short leases so that recovery after a kill takes seconds in tests."""


def write_scan_file(settings: Settings, name: str, points: NDArray[np.float64]) -> str:
    """Store ``points`` as an NPY scan file; its path relative to the data dir."""
    relative = f"scans/{name}"
    path = settings.data_dir / relative
    path.parent.mkdir(parents=True, exist_ok=True)
    np.save(path, points)
    return relative


def create_job(
    settings: Settings,
    *,
    scan_filename: str = "scan.npy",
    n_points: int = 2000,
    params: dict[str, Any] | None = None,
    max_attempts: int | None = None,
    scan_bytes: bytes | None = None,
) -> str:
    """Insert organisation, site, reference and scan (files on disk) and a queued job; its id."""
    with transaction(settings.sqlalchemy_url) as session:
        organisation = session.scalar(select(Organisation).where(Organisation.name == "tests"))
        if organisation is None:
            organisation = Organisation(name="tests")
            session.add(organisation)
            session.flush()
        site = Site(organisation_id=organisation.id, name=f"site-{os.urandom(4).hex()}")
        session.add(site)
        session.flush()
        scans = []
        for role, added in (("reference", False), ("scan", True)):
            points = corridor_points(n_points, added_box=added, seed=len(role))
            scan = Scan(
                organisation_id=organisation.id,
                site_id=site.id,
                filename=scan_filename if role == "scan" else "reference.npy",
                format="npy",
                size_bytes=int(points.nbytes),
                sha256="0" * 64,
                storage_path="",
                n_points=len(points),
                bbox_min=points.min(axis=0).tolist(),
                bbox_max=points.max(axis=0).tolist(),
            )
            session.add(scan)
            session.flush()
            scan.storage_path = write_scan_file(settings, f"{scan.id}.npy", points)
            if role == "scan" and scan_bytes is not None:
                (settings.data_dir / scan.storage_path).write_bytes(scan_bytes)
            scans.append(scan)
        job = new_job(
            site,
            scans[0].id,
            scans[1].id,
            params=params or {},
            status="queued",
            max_attempts=max_attempts or settings.job_max_attempts,
        )
        session.add(job)
        session.flush()
        return job.id


def load_job(settings: Settings, job_id: str) -> Job:
    """The job row as stored now."""
    with transaction(settings.sqlalchemy_url) as session:
        job = session.get(Job, job_id)
        assert job is not None
        session.expunge(job)
        return job


def count_regions(settings: Settings, job_id: str) -> int:
    """How many Region rows job ``job_id`` has."""
    with transaction(settings.sqlalchemy_url) as session:
        return int(session.scalar(select(func.count()).where(Region.job_id == job_id)) or 0)


def wait_for_status(
    settings: Settings, job_id: str, statuses: tuple[str, ...], timeout: float = 30.0
) -> Job:
    """Poll the job row until its status is one of ``statuses``."""
    deadline = time.monotonic() + timeout
    job = load_job(settings, job_id)
    while time.monotonic() < deadline:
        job = load_job(settings, job_id)
        if job.status in statuses:
            return job
        time.sleep(0.05)
    raise TimeoutError(
        f"job {job_id} still {job.status} ({job.stage}, {job.error}) after {timeout}s"
    )


def finish_job(
    api: ApiServer,
    job_id: str,
    n_reference: int,
    n_scan: int,
    *,
    changed: bool = True,
    transform: list[list[float]] | None = None,
    **result_fields: Any,
) -> dict[str, NDArray]:
    """Play the worker on queued job ``job_id``: claim it, write its result files and rows
    through the real ``claim_job``, ``write_result_files`` and ``store_results`` (one added
    region, random labels and distances; ``result_fields`` replace fields of the
    ``ComparisonResult``, e.g. ``regions``, ``registration``, ``sensor_origins``); the
    per-point arrays written."""
    rng = np.random.default_rng(7)
    reference_label = rng.integers(-1, 2, n_reference).astype(np.int8)
    scan_label = rng.integers(-1, 2, n_scan).astype(np.int8)
    reference_distance = rng.uniform(0, 1, n_reference).astype(np.float32)
    scan_distance = rng.uniform(0, 1, n_scan).astype(np.float32)
    settings = api.settings
    job = claim_job(job_id, settings, make_lease_owner())
    assert job is not None, f"job {job_id} could not be claimed"
    result = ComparisonResult(
        method=job.method,
        variant=job.variant,
        params=job.params,
        score=0.5,
        threshold=0.1,
        changed=changed,
        calibration=calibration_report(changed=changed),
        registration=registration_report(transform=transform or np.eye(4).tolist()),
        regions=[
            RegionSummary("added", 12, [1.0, 2.0, 0.5], [0.5, 1.5, 0.0], [1.5, 2.5, 1.0], 0.4, 0.9)
        ],
        n_reference=n_reference,
        n_scan=n_scan,
        reference_label=reference_label,
        scan_label=scan_label,
        reference_distance=reference_distance,
        scan_distance=scan_distance,
        reference_region=np.full(n_reference, -1, dtype=np.int32),
        scan_region=np.full(n_scan, -1, dtype=np.int32),
    )
    result = dataclasses.replace(result, **result_fields)
    labels_path = write_result_files(job, settings, result)
    assert store_results(job, settings, result, labels_path, {"align": 0.1})
    return {
        "reference_label": reference_label,
        "scan_label": scan_label,
        "reference_changed": reference_label == 1,
        "scan_changed": scan_label == 1,
        "reference_distance": reference_distance,
        "scan_distance": scan_distance,
    }


def random_regions(count: int, seed: int) -> list[RegionSummary]:
    """``count`` regions of both kinds with random sizes, positions and distances."""
    rng = np.random.default_rng(seed)
    regions = []
    for _ in range(count):
        low = rng.uniform(-5, 5, 3)
        high = low + rng.uniform(0.05, 2.0, 3)
        mean_distance = float(rng.uniform(0.05, 0.5))
        regions.append(
            RegionSummary(
                str(rng.choice(["added", "removed"])),
                int(rng.integers(5, 5000)),
                ((low + high) / 2).tolist(),
                low.tolist(),
                high.tolist(),
                mean_distance,
                mean_distance + float(rng.uniform(0, 0.5)),
            )
        )
    return regions
