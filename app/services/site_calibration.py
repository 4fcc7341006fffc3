"""A site's learned thresholds (:func:`app.core.site_calibration.learn_site_calibration`) from
its *reviewed-null* jobs of its current detector; recomputed on each verdict and when the site's
detector changes (the samples of another detector do not apply)."""

from __future__ import annotations

from collections import defaultdict
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.clock import utc_now
from app.config import Settings
from app.core.jsonable import json_safe
from app.core.site_calibration import ReviewedSample, largest_extent, learn_site_calibration
from app.db.models import Job, JobStatus, Region, Site


def is_reviewed_null(verdict: dict[str, Any] | None, changed: bool | None) -> bool:
    """Whether a job's current verdict says nothing really changed (a calibration sample)."""
    if not verdict:
        return False
    kind = verdict.get("verdict")
    return kind == "false_alarm" or (kind == "confirmed" and changed is False)


def reviewed_samples(session: Session, site: Site) -> list[ReviewedSample]:
    """The site's reviewed-null succeeded jobs of its current detector, oldest first."""
    rows = session.scalars(
        select(Job)
        .where(
            Job.site_id == site.id,
            Job.status == JobStatus.SUCCEEDED,
            Job.verdict.is_not(None),
            Job.method == site.detector_method,
            Job.variant == site.detector_variant,
        )
        .order_by(Job.created_at, Job.id)
    ).all()
    chosen = [job for job in rows if is_reviewed_null(job.verdict, job.changed)]
    regions: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for job_id, n_points, bbox_min, bbox_max in session.execute(
        select(Region.job_id, Region.n_points, Region.bbox_min, Region.bbox_max)
        .where(Region.job_id.in_([job.id for job in chosen]))
        .order_by(Region.job_id, Region.ordinal)  # the job's order: the first of equals wins
    ):
        regions[job_id].append({"n_points": n_points, "bbox_min": bbox_min, "bbox_max": bbox_max})
    return [
        ReviewedSample(
            job_id=job.id,
            score=float(job.score) if job.score is not None else 0.0,
            largest_region_extent_m=largest_extent(regions[job.id]),
        )
        for job in chosen
    ]


def recompute_site_calibration(session: Session, settings: Settings, site: Site) -> None:
    """Learn the site's thresholds again from its reviewed-null jobs (stored on the site)."""
    site.calibration = json_safe(
        {
            **learn_site_calibration(
                reviewed_samples(session, site),
                method=site.detector_method,
                variant=site.detector_variant,
                false_alarm_rate=settings.site_false_alarm_rate,
                min_samples=settings.site_calibration_min_samples,
            ),
            "computed_at": utc_now().isoformat(),
        }
    )
    session.flush()
