"""The ray test from the other epoch's stations: the visibility test for clouds whose sensor
origins are known (given, in the file, estimated or recovered).

Each station's own returns are its rays (:mod:`app.core.localise.rays`); a candidate is
observed when any station saw it (:func:`combine_station_status`).  A candidate whose surface
the stations saw only edge-on gets no evidence of its own: it is changed when connected to
candidates mostly seen through (a removed box's side face), unobserved otherwise
(:func:`resolve_edge_on`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.core.localise.distance import Side
from app.core.localise.interface import INDIRECT_CONFIDENCE, VisibilityContext, VisibilityOutcome
from app.core.localise.rays import (
    STATUS_EDGE_ON,
    STATUS_SEEN_THROUGH,
    STATUS_SURFACE,
    STATUS_UNOBSERVED,
    Candidates,
    RayTest,
    ray_visibility,
)
from app.core.localise.regions import cluster_labels

__all__ = [
    "StationRayTest",
    "combine_station_status",
    "ray_test_for",
    "resolve_edge_on",
    "settle_ray_status",
]

EDGE_ON_SEEN_THROUGH_SHARE = 0.5
MIN_STATION_POINTS = 10
"""A station of the other cloud with fewer returns than this is ignored (it saw nothing)."""


def ray_test_for(own: Side, other: Side, context: VisibilityContext) -> RayTest:
    """The ray test's tolerances for ``own``'s candidates seen from ``other``'s sensor."""
    settings = context.settings
    return RayTest(
        normal_tolerance=settings["threshold_factor"]
        * math.hypot(own.geometry.noise, context.misalignment),
        range_tolerance=settings["threshold_factor"] * other.geometry.noise,
        margin_factor=settings["visibility_margin_factor"],
        angle_factor=settings["visibility_angle_factor"],
        beyond_fraction=settings["visibility_beyond_fraction"],
        miss_factor=settings["visibility_miss_factor"],
    )


class StationRayTest:
    """The ray test from each station of the other cloud (``name = "ray"``)."""

    name = "ray"

    def __call__(
        self, candidates: Candidates, *, own: Side, other: Side, context: VisibilityContext
    ) -> VisibilityOutcome:
        """Statuses from the other cloud's stations, edge-on faces settled."""
        status, steps = any_station_status(
            candidates,
            own=own,
            other=other,
            test=ray_test_for(own, other, context),
            threads=context.threads,
        )
        report: dict[str, Any] = {
            "other_stations": len(steps),
            "other_angular_step_deg": math.degrees(float(np.median(steps))),
        }
        return settle_ray_status(candidates, status, report, context)


def settle_ray_status(
    candidates: Candidates,
    status: NDArray[np.int8],
    report: dict[str, Any],
    context: VisibilityContext,
) -> VisibilityOutcome:
    """Count the ray statuses, resolve the edge-on ones, and give indirect ones less confidence.

    Parameters
    ----------
    candidates : Candidates
    status : ndarray, shape (c,), int8
        Ray statuses, STATUS_EDGE_ON included.
    report : dict
        The test's figures so far; the counts are added to it.
    context : VisibilityContext

    Returns
    -------
    VisibilityOutcome
    """
    report["candidates_on_other_surface"] = int((status == STATUS_SURFACE).sum())
    report["candidates_edge_on"] = int((status == STATUS_EDGE_ON).sum())
    direct = status == STATUS_SEEN_THROUGH
    status = resolve_edge_on(
        candidates.points,
        spacing=candidates.spacing,
        status=status,
        cluster_factor=context.settings["cluster_factor"],
    )
    confidence = np.where(direct, 1.0, INDIRECT_CONFIDENCE).astype(np.float32)
    return VisibilityOutcome(status=status, confidence=confidence, report=report)


def any_station_status(
    candidates: Candidates, *, own: Side, other: Side, test: RayTest, threads: int = 1
) -> tuple[NDArray[np.int8], list[float]]:
    """Ray status of each candidate as seen by any station of the other cloud.

    Each station's rays are its own returns (``other.station``; all of them with one
    station), with their surfaces' normals; the statuses are combined by
    :func:`combine_station_status`.  ``threads``: chunks of candidates tested at once.

    Returns
    -------
    status : ndarray, shape (c,), int8
    angular_steps : list of float
        Each station's typical angular step (radians).
    """
    assert other.origins is not None
    statuses = []
    angular_steps = []
    for number, origin in enumerate(other.origins):
        normal, linear = other.geometry.normal, other.geometry.linear
        if other.station is None:
            station_points = other.points
        else:
            mine = other.station == number
            station_points, normal, linear = other.points[mine], normal[mine], linear[mine]
        if station_points.shape[0] < MIN_STATION_POINTS:
            continue  # a station without returns saw nothing: all unobserved
        status, angular_step = ray_visibility(
            candidates,
            own=own.geometry,
            other_points=station_points,
            other_origin=origin,
            test=test,
            other_normals=normal,
            other_linear=linear,
            threads=threads,
        )
        statuses.append(status)
        angular_steps.append(angular_step)
    if not statuses:
        return np.full(candidates.index.shape[0], STATUS_UNOBSERVED, dtype=np.int8), [math.nan]
    return combine_station_status(np.stack(statuses)), angular_steps


def combine_station_status(statuses: NDArray[np.int8]) -> NDArray[np.int8]:
    """One status per candidate from each station's: observed by any station.

    Parameters
    ----------
    statuses : ndarray, shape (k, c), int8
        :func:`~app.core.localise.rays.ray_visibility` status from each of k stations.

    Returns
    -------
    ndarray, shape (c,), int8
        Seen through when at least one station saw through it and no more stations saw a
        surface there; else surface when a station saw one; else edge-on when a station saw
        its surface edge-on; else unobserved (no station could see it).  With k = 1 the
        station's own status.
    """
    if statuses.shape[0] == 1:
        return statuses[0]
    through = (statuses == STATUS_SEEN_THROUGH).sum(axis=0)
    surface = (statuses == STATUS_SURFACE).sum(axis=0)
    edge_on = (statuses == STATUS_EDGE_ON).any(axis=0)
    combined = np.where(edge_on, STATUS_EDGE_ON, STATUS_UNOBSERVED)
    combined = np.where(surface > 0, STATUS_SURFACE, combined)
    combined = np.where((through > 0) & (through >= surface), STATUS_SEEN_THROUGH, combined)
    return combined.astype(np.int8)


def resolve_edge_on(
    points: NDArray[np.float64],
    *,
    spacing: NDArray[np.float64],
    status: NDArray[np.int8],
    cluster_factor: float,
) -> NDArray[np.int8]:
    """Decide candidates whose surface the other sensor saw only edge-on.

    A removed box's face that the other sensor sees edge-on gets no ray evidence of its own,
    but the sensor saw through the rest of the box: edge-on candidates connected (within
    ``cluster_factor`` local spacings) to candidates that are mostly seen through are
    changed; the others (a pillar's face seen edge-on, the rest unchanged) are unobserved.

    Parameters
    ----------
    points : ndarray, shape (c, 3)
        The candidates.
    spacing : ndarray, shape (c,)
        Their cloud's local spacing.
    status : ndarray, shape (c,), int8
        From :func:`ray_visibility`.
    cluster_factor : float

    Returns
    -------
    ndarray, shape (c,), int8
        ``status`` with every STATUS_EDGE_ON replaced.
    """
    edge_on = status == STATUS_EDGE_ON
    if not edge_on.any():
        return status
    involved = np.flatnonzero(edge_on | (status == STATUS_SEEN_THROUGH))
    labels = cluster_labels(points[involved], cluster_factor * spacing[involved])
    seen_through_share = np.bincount(
        labels, weights=(status[involved] == STATUS_SEEN_THROUGH).astype(np.float64)
    ) / np.bincount(labels)
    promoted = seen_through_share[labels] >= EDGE_ON_SEEN_THROUGH_SHARE
    resolved = status.copy()
    resolved[involved] = np.where(
        edge_on[involved],
        np.where(promoted, STATUS_SEEN_THROUGH, STATUS_UNOBSERVED),
        status[involved],
    )
    return resolved
