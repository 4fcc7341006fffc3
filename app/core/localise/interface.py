"""The one small interface every visibility test implements.

A visibility test takes one cloud's change candidates and says, for each, whether the other
epoch saw its place empty (changed), saw a surface there (unchanged) or could not see it
(unobserved).  The tests differ in what they know of the other epoch: its sensor origins
(:class:`~app.core.localise.station_rays.StationRayTest`), its trajectory
(:class:`~app.core.localise.trajectory_visibility.TrajectoryTest`), or only its surfaces
(:class:`~app.core.localise.map_evidence.MapTest`,
:class:`~app.core.localise.origin_free.SurfaceTest`,
:class:`~app.core.localise.coverage.CoverageTest`).
:func:`~app.core.localise.visibility.choose_test` picks one per cloud and the result reports
which (``<side>_visibility``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from app.core.localise.distance import Side
from app.core.localise.rays import Candidates

__all__ = [
    "INDIRECT_CONFIDENCE",
    "FaceBorder",
    "VisibilityContext",
    "VisibilityOutcome",
    "VisibilityTest",
]

INDIRECT_CONFIDENCE = 0.5
"""Confidence of a change a test could not see directly: an edge-on face joined to faces seen
through, or a candidate the coverage test kept."""


@dataclass(frozen=True)
class VisibilityContext:
    """What every visibility test may use besides the two clouds.

    Attributes
    ----------
    misalignment : float
        registration_rmse and the measured alignment residual combined (metres).
    threshold : float
        ``tau``: the noise-resolved plane tolerance (metres).
    change_threshold : float
        ``c``: a surface within it is the same surface (metres).
    settings : mapping
        The resolved localisation parameters.
    threads : int
        Threads a test may keep busy (the same result on any number).
    shared : mapping, optional
        What a test computes once per comparison for both clouds' tests, by cloud name
        (the map test's metric-scale planes); a test computes its own without it.
    """

    misalignment: float
    threshold: float
    change_threshold: float
    settings: Mapping[str, Any]
    threads: int = 1
    shared: Mapping[str, Any] | None = None


@dataclass(frozen=True)
class FaceBorder:
    """One cloud's unseen faces, as the map test found them
    (:func:`~app.core.localise.map_agreement.faces_meeting_changes` reads them).

    Attributes
    ----------
    members : ndarray, shape (f,), int64
        The cloud's points (indices) in parts that are coverage differences as unseen faces.
    member_part : ndarray, shape (f,), int64
        Each member's part number.
    border : ndarray, shape (b,), int64
        The members that lie on their part's border and that the other epoch's surface meets
        at an edge (point indices).
    border_part : ndarray, shape (b,), int64
        Each border point's part number.
    """

    members: NDArray[np.int64]
    member_part: NDArray[np.int64]
    border: NDArray[np.int64]
    border_part: NDArray[np.int64]


@dataclass(frozen=True)
class VisibilityOutcome:
    """One test's verdict on one cloud's candidates.

    Attributes
    ----------
    status : ndarray, shape (c,), int8
        STATUS_SEEN_THROUGH (changed), STATUS_SURFACE (unchanged) or STATUS_UNOBSERVED.
    confidence : ndarray, shape (c,), float32
        Confidence in each candidate's status, in [0, 1].
    report : dict
        JSON-serialisable figures (the result reports them prefixed with the side's name).
    evidence : ndarray, shape (c,), int8, optional
        :data:`~app.core.localise.regions.EVIDENCE_NAMES` code of each candidate; default:
        seen_empty for changed, no_coverage for unobserved candidates.
    faces : FaceBorder, optional
        The map test's unseen faces, which the two sides' verdicts may overturn
        (:func:`~app.core.localise.map_agreement.faces_meeting_changes`).
    """

    status: NDArray[np.int8]
    confidence: NDArray[np.float32]
    report: dict[str, Any] = field(default_factory=dict)
    evidence: NDArray[np.int8] | None = None
    faces: FaceBorder | None = None


class VisibilityTest(Protocol):
    """A visibility test: a name the result reports, and a call on one cloud's candidates."""

    name: str

    def __call__(
        self, candidates: Candidates, *, own: Side, other: Side, context: VisibilityContext
    ) -> VisibilityOutcome:
        """Judge ``own``'s candidates against what the ``other`` epoch saw."""
        ...
