"""The coverage test: a candidate far from every point of the other cloud is unobserved.

Without a viewpoint a removed object and a hole in the other cloud's coverage look alike; the
test calls a candidate unobserved when its nearest point in the other cloud is farther than
``coverage_factor`` of that point's local spacings, changed otherwise.  It suits merged
multi-view maps sampled coarsely (the paper's corridor); the map test
(:mod:`app.core.localise.map_evidence`) replaced it as the default.  With
``origin_free_test="gaps"`` a candidate lying on the other cloud's surface between its samples
(:func:`~app.core.localise.gaps.in_sampling_gap`) is unchanged first.
"""

from __future__ import annotations

import numpy as np

from app.core.localise.distance import Side
from app.core.localise.gaps import in_sampling_gap
from app.core.localise.interface import INDIRECT_CONFIDENCE, VisibilityContext, VisibilityOutcome
from app.core.localise.rays import (
    STATUS_SEEN_THROUGH,
    STATUS_SURFACE,
    STATUS_UNOBSERVED,
    Candidates,
)

__all__ = ["CoverageTest"]


class CoverageTest:
    """The coverage test (``name = "coverage"``), optionally after the sampling-gap test."""

    name = "coverage"

    def __init__(self, *, sampling_gaps: bool = False) -> None:
        self.sampling_gaps = sampling_gaps

    def __call__(
        self, candidates: Candidates, *, own: Side, other: Side, context: VisibilityContext
    ) -> VisibilityOutcome:
        """Unobserved beyond ``coverage_factor`` spacings of the other cloud, else changed."""
        index = candidates.index
        covered = (
            own.nearest_distance[index]
            <= context.settings["coverage_factor"]
            * other.geometry.spacing[own.nearest_index[index]]
        )
        status = np.where(covered, STATUS_SEEN_THROUGH, STATUS_UNOBSERVED).astype(np.int8)
        report = {}
        if self.sampling_gaps:
            gap = in_sampling_gap(
                candidates.points,
                candidates.normal,
                own.nearest_distance[index],
                other=other.geometry,
                tolerance=context.threshold,
            )
            report["candidates_in_sampling_gaps"] = int(gap.sum())
            status = np.where(gap, STATUS_SURFACE, status).astype(np.int8)
        confidence = np.full(index.shape[0], INDIRECT_CONFIDENCE, dtype=np.float32)
        return VisibilityOutcome(status=status, confidence=confidence, report=report)
