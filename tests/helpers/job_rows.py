"""Job rows built directly, light to import (SQLAlchemy models only): spawned processes use it."""

from __future__ import annotations

from typing import Any

from app.db.models import Job, Site


def new_job(site: Site, reference_scan_id: str, scan_id: str, **columns: Any) -> Job:
    """A Job row of ``site`` comparing two scans with the default detector; ``columns`` added."""
    return Job(
        organisation_id=site.organisation_id,
        site_id=site.id,
        reference_scan_id=reference_scan_id,
        scan_id=scan_id,
        method="gmm",
        variant="improved",
        **columns,
    )
