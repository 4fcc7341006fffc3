"""Warnings that need the site's history: a region count far above the site's usual.

A comparison that finds 139 regions where the site's comparisons usually find 2 is more
likely a bad pairing or alignment than a real change; the job says so.  Checked when the job's
results are stored (:func:`app.jobs.results.store_results`), against the site's previous
succeeded jobs at that moment.  The warning is a :class:`RegionCountWarning`, stored as its
:meth:`~RegionCountWarning.to_json_dict` beside the core's quality warnings (same keys:
``code``, ``message``, the measured values, ``detail``, ``how_to_fix``).
"""

from __future__ import annotations

import statistics
from dataclasses import dataclass
from typing import Any, ClassVar

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


@dataclass(frozen=True)
class RegionCountWarning:
    """A job's region count far above its site's usual: ``region_count_above_history``.

    Attributes
    ----------
    n_regions : int
        The job's region count (the warning's ``value``).
    limit : float
        The count above which it warns: ``max(REGION_COUNT_FACTOR * median, median +
        REGION_COUNT_MIN_EXCESS)``.
    median : float
        The median region count of the site's history.
    history_jobs : int
        How many of the site's previous succeeded jobs made that history.
    """

    n_regions: int
    limit: float
    median: float
    history_jobs: int

    code: ClassVar[str] = "region_count_above_history"
    action: ClassVar[str] = "check_site_history"
    explanation: ClassVar[str] = (
        "so many regions more often come from a bad alignment or a scan of another place than "
        "from real change"
    )

    @property
    def message(self) -> str:
        """One sentence: the count, the site's usual and how many jobs make it."""
        return (
            f"{self.n_regions} regions, far above this site's usual {self.median:g} (the median "
            f"of its last {self.history_jobs} comparisons)."
        )

    def to_json_dict(self) -> dict[str, Any]:
        """``{"code", "message", "value", "limit", "median", "history_jobs", "detail",
        "how_to_fix"}``, as stored in the job's ``warnings``."""
        measured = {
            "value": self.n_regions,
            "limit": self.limit,
            "median": self.median,
            "history_jobs": self.history_jobs,
        }
        return {
            "code": self.code,
            "message": self.message,
            **measured,
            "detail": {**measured, "explanation": self.explanation},
            "how_to_fix": {"action": self.action},
        }


def region_count_warning(session: Session, job: Job, n_regions: int) -> RegionCountWarning | None:
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
    return RegionCountWarning(
        n_regions=n_regions, limit=limit, median=median, history_jobs=len(history)
    )
