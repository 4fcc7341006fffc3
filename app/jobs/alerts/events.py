"""The events of a finished job: ``job.changed``, ``job.unchanged`` and ``job.failed``.

:func:`publish_job_finished` is called in the transaction that finishes the job (results
stored, or failed for good), so that the event exists exactly when the job's new state does.
The payload names the site and the job, with score, threshold, decision and a summary of the
regions; the signed view link is added per webhook when a delivery is sent
(:mod:`app.jobs.alerts.deliveries`), since it names the token that created the webhook.
"""

from __future__ import annotations

from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.clock import iso_utc
from app.db.events import publish_event
from app.db.models import Job, JobStatus, Region, Site

LARGEST_REGIONS = 5
"""Regions listed one by one in a payload (the largest by points); the rest are counted."""


def region_summary(session: Session, job_id: str) -> dict[str, Any]:
    """Counts of the job's regions by kind, changed points, and the largest few."""
    regions = session.scalars(select(Region).where(Region.job_id == job_id)).all()
    largest = sorted(regions, key=lambda region: region.n_points, reverse=True)[:LARGEST_REGIONS]
    return {
        "count": len(regions),
        "added": sum(1 for region in regions if region.kind == "added"),
        "removed": sum(1 for region in regions if region.kind == "removed"),
        "changed_points": sum(region.n_points for region in regions),
        "largest": [
            {
                "kind": region.kind,
                "n_points": region.n_points,
                "centroid": region.centroid,
                "bbox_min": region.bbox_min,
                "bbox_max": region.bbox_max,
                "max_distance": region.max_distance,
            }
            for region in largest
        ],
    }


def job_event_payload(session: Session, job: Job) -> dict[str, Any]:
    """What a receiver learns about a finished job (without the view link)."""
    site = session.get(Site, job.site_id)
    decision = None if job.changed is None else ("changed" if job.changed else "unchanged")
    return {
        "site": {"id": job.site_id, "name": site.name if site is not None else None},
        "job": {
            "id": job.id,
            "status": str(job.status),
            "scan_id": job.scan_id,
            "reference_scan_id": job.reference_scan_id,
            "method": job.method,
            "variant": job.variant,
            "attempts": job.attempts,
            "created_at": iso_utc(job.created_at) if job.created_at else None,
            "finished_at": iso_utc(job.finished_at) if job.finished_at else None,
            "error": job.error,
        },
        "score": job.score,
        "threshold": job.threshold,
        "decision": decision,
        "regions": region_summary(session, job.id),
    }


def publish_job_finished(session: Session, job_id: str) -> None:
    """Publish the event of job ``job_id``'s final state, in ``session``'s transaction."""
    session.flush()
    job = session.get(Job, job_id, populate_existing=True)
    if job is None:
        return
    if job.status == JobStatus.FAILED:
        event_type = "job.failed"
    elif job.status == JobStatus.SUCCEEDED:
        event_type = "job.changed" if job.changed else "job.unchanged"
    else:
        return
    publish_event(
        session,
        organisation_id=job.organisation_id,
        event_type=event_type,
        payload=job_event_payload(session, job),
    )
