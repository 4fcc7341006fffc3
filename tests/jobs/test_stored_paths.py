"""A scan row whose stored path leads outside the data directory: the job fails saying so,
without reading the file (real SQLite migrated by Alembic, the worker's own code)."""

from __future__ import annotations

from pathlib import Path

from sqlalchemy import update

from app.config import Settings
from app.db.models import Job, Scan
from app.db.session import transaction
from app.jobs.execution import execute_job
from tests.helpers.jobs import create_job, load_job


def test_a_stored_path_outside_the_data_directory_fails_the_job(
    job_settings: Settings, tmp_path: Path
) -> None:
    job_id = create_job(job_settings)
    outside = tmp_path / "outside.npy"
    outside.write_bytes(b"not a scan of this service")
    with transaction(job_settings.sqlalchemy_url) as session:
        scan_id = session.get(Job, job_id).scan_id  # type: ignore[union-attr]
        session.execute(update(Scan).where(Scan.id == scan_id).values(storage_path=str(outside)))

    assert execute_job(job_id, job_settings) == "failed"

    job = load_job(job_settings, job_id)
    assert job.status == "failed"
    assert f"stored path {str(outside)!r} points outside the data directory" in (job.error or "")
