"""Warnings that need the site's history: a region count far above the site's usual.

A comparison that finds 139 regions where the site's comparisons usually find 2 is more
likely a bad pairing or alignment than a real change; the job says so.  Checked when the job's
results are stored (:func:`app.jobs.results.store_results`), against the site's previous
succeeded jobs at that moment.
"""

from __future__ import annotations

import statistics
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.db.models import Job, JobStatus

HISTORY_JOBS = 20
"""How many of the site's latest succeeded jobs make its history."""

HISTORY_MIN_JOBS = 3
"""Fewer previous jobs than this: no history to compare with, no warning."""

REGION_COUNT_FACTOR = 3.0
"""A region count above this many times the history's median is "far above"..."""

REGION_COUNT_MIN_EXCESS = 5
"""...and at least this many regions above it (2 regions against a median of 0 is not)."""


def region_count_warning(session: Session, job: Job, n_regions: int) -> dict[str, Any] | None:
    """The ``region_count_above_history`` warning for ``job`` finding ``n_regions``, or None."""
    history = list(
        session.scalars(
            select(Job.n_regions)
            .where(
                Job.site_id == job.site_id,
                Job.id != job.id,
                Job.status == JobStatus.SUCCEEDED,
                Job.n_regions.is_not(None),
                Job.created_at <= job.created_at,
            )
            .order_by(Job.created_at.desc())
            .limit(HISTORY_JOBS)
        )
    )
    if len(history) < HISTORY_MIN_JOBS:
        return None
    median = float(statistics.median(history))
    limit = max(REGION_COUNT_FACTOR * median, median + REGION_COUNT_MIN_EXCESS)
    if n_regions <= limit:
        return None
    measured = {
        "value": n_regions,
        "limit": limit,
        "median": median,
        "history_jobs": len(history),
    }
    return {
        "code": "region_count_above_history",
        "message": f"{n_regions} regions, far above this site's usual {median:g} (the median of "
        f"its last {len(history)} comparisons).",
        **measured,
        "detail": {
            **measured,
            "explanation": "so many regions more often come from a bad alignment or a scan of "
            "another place than from real change",
        },
        "how_to_fix": {"action": "check_site_history"},
    }
