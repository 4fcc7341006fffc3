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
from app.core.localise.surface import principal_axes

__all__ = [
    "StationRayTest",
    "combine_station_status",
    "ray_test_for",
    "resolve_edge_on",
    "settle_ray_status",
]

EDGE_ON_SEEN_THROUGH_SHARE = 0.5
EDGE_ON_SEEN_THROUGH_FLOOR = 0.1
EDGE_ON_THROUGH_OVER_SURFACE = 3.0
EDGE_ON_THICKNESS_FACTOR = 0.5
"""Such a cluster thinner than this many ``c`` (standard deviation along its thinnest axis) is
one sheet (a removed box's only sampled face: TLS 2504's top, 0.012 m; a rack's shelf edge),
not an object's several faces (TLS 204: 0.095 m, 2104's chair 0.10 m), and needs its evidence
inside its outline (:data:`SHEET_RIM_FACTOR`)."""
SHEET_RIM_FACTOR = 2.0
"""A sheet's edge-on candidates are changed only when, among its candidates more than this many
local spacings inside its outline (its convex hull in its plane), at least
:data:`EDGE_ON_SEEN_THROUGH_FLOOR` were seen through: a ray passing beside a grazed sheet's rim
crosses its plane just past its last points (a near miss, no evidence it is gone), a ray
through its interior crosses where the sheet must be (TLS 2504: the box top seen at 85 deg by
one station, 28 % seen through all over it; TLS 2604's added board: its 11 seen-through
candidates of 248, 10 of them within 6 cm of its outline, come from rays passing 4-6 cm beside
it, none crossing inside it)."""
EDGE_ON_CLEAR_FACTOR = 2.5
"""A surveyed cloud's edge-on candidates are also changed when, among the candidates connected
to them (those seen as a surface included), at least :data:`EDGE_ON_SEEN_THROUGH_FLOOR` were seen
through and :data:`EDGE_ON_THROUGH_OVER_SURFACE` times more often than seen as a surface, and
the edge-on ones lie clear of the other cloud (their median distance to its surface at least
this many ``c``): a far station's rays (15-25 cm apart) rarely meet a box's faces near a point
of them but pass through the box (TLS 204: 58 edge-on, 15 seen through, none a surface, 0.39 m
from the other cloud; 2104's chair 96 / 23, 0.40 m); an unchanged surface the other epoch
sampled sparsely or in part lies within a couple of ``c`` of its points (TLS 2000's board
0.17 m, 2104's thin panels 0.11-0.12 m, with ``c`` = 0.1 m)."""
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
        surveyed = len(steps) > 1
        return settle_ray_status(candidates, status, report, context, surveyed=surveyed)


def settle_ray_status(
    candidates: Candidates,
    status: NDArray[np.int8],
    report: dict[str, Any],
    context: VisibilityContext,
    *,
    surveyed: bool = False,
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
    surveyed : bool
        The other cloud's rays came from several stations (a survey): edge-on clusters seen
        through rather than as a surface, clear of the other cloud, are changed too
        (:data:`EDGE_ON_CLEAR_FACTOR`).

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
        clear_of_other=(
            candidates.surface_distance >= EDGE_ON_CLEAR_FACTOR * context.change_threshold
            if surveyed
            else None
        ),
        min_thickness=EDGE_ON_THICKNESS_FACTOR * context.change_threshold,
        threads=context.threads,
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
    clear_of_other: NDArray[np.bool_] | None = None,
    min_thickness: float = 0.0,
    threads: int = 1,
) -> NDArray[np.int8]:
    """Decide candidates whose surface the other sensor saw only edge-on.

    A removed box's face that the other sensor sees edge-on gets no ray evidence of its own,
    but the sensor saw through the rest of the box: edge-on candidates connected (within
    ``cluster_factor`` local spacings) to candidates that are mostly seen through are
    changed; with ``clear_of_other``, so are those of a cluster (surface candidates included)
    seen through rather than as a surface whose edge-on candidates are mostly clear of the
    other cloud (:data:`EDGE_ON_CLEAR_FACTOR`: a far station's rays through a box whose faces
    they miss); the others (a pillar's face seen edge-on, the rest unchanged) are unobserved.

    Parameters
    ----------
    points : ndarray, shape (c, 3)
        The candidates.
    spacing : ndarray, shape (c,)
        Their cloud's local spacing.
    status : ndarray, shape (c,), int8
        From :func:`ray_visibility`.
    cluster_factor : float
    clear_of_other : ndarray, shape (c,), bool, optional
        The candidate lies at least :data:`EDGE_ON_CLEAR_FACTOR` ``c`` from the other cloud's
        surface; None: only the seen-through share decides.
    min_thickness : float
        With ``clear_of_other``: such a cluster's points must spread at least this far (the
        standard deviation along their thinnest axis) off one plane (an object's several
        faces, not one grazed sheet).
    threads : int
        Threads of the clusters' neighbour search (:func:`cluster_labels`; the same clusters).

    Returns
    -------
    ndarray, shape (c,), int8
        ``status`` with every STATUS_EDGE_ON replaced.
    """
    edge_on = status == STATUS_EDGE_ON
    if not edge_on.any():
        return status
    involved = np.flatnonzero(edge_on | (status == STATUS_SEEN_THROUGH))
    labels = cluster_labels(points[involved], cluster_factor * spacing[involved], threads)
    seen_through_share = np.bincount(
        labels, weights=(status[involved] == STATUS_SEEN_THROUGH).astype(np.float64)
    ) / np.bincount(labels)
    promoted = seen_through_share[labels] >= EDGE_ON_SEEN_THROUGH_SHARE
    if clear_of_other is not None:
        promoted |= _seen_through_clear_of_other(
            points,
            spacing=spacing,
            status=status,
            cluster_factor=cluster_factor,
            clear=clear_of_other,
            min_thickness=min_thickness,
        )[involved]
    resolved = status.copy()
    resolved[involved] = np.where(
        edge_on[involved],
        np.where(promoted, STATUS_SEEN_THROUGH, STATUS_UNOBSERVED),
        status[involved],
    )
    return resolved


def _seen_through_clear_of_other(
    points: NDArray[np.float64],
    *,
    spacing: NDArray[np.float64],
    status: NDArray[np.int8],
    cluster_factor: float,
    clear: NDArray[np.bool_],
    min_thickness: float,
) -> NDArray[np.bool_]:
    """Whether each candidate (shape (c,)) lies in a cluster of edge-on, seen-through and
    surface candidates at least :data:`EDGE_ON_SEEN_THROUGH_FLOOR` seen through, seen through
    :data:`EDGE_ON_THROUGH_OVER_SURFACE` times more often than seen as a surface, and whose
    edge-on candidates are mostly ``clear`` of the other cloud, and that is at least
    ``min_thickness`` thick (:func:`_thickness`) or, one sheet, seen through inside its
    outline (:func:`_sheet_seen_through_inside`); clusters as in :func:`resolve_edge_on`."""
    edge_on = status == STATUS_EDGE_ON
    surface = status == STATUS_SURFACE
    through = status == STATUS_SEEN_THROUGH
    involved = np.flatnonzero(edge_on | through | surface)
    labels = cluster_labels(points[involved], cluster_factor * spacing[involved])
    n_through = np.bincount(labels, weights=through[involved].astype(np.float64))
    n_surface = np.bincount(labels, weights=surface[involved].astype(np.float64))
    n_edge_on = np.bincount(labels, weights=edge_on[involved].astype(np.float64))
    n_clear = np.bincount(labels, weights=(edge_on & clear)[involved].astype(np.float64))
    cluster = (
        (n_through >= EDGE_ON_SEEN_THROUGH_FLOOR * np.bincount(labels))
        & (n_through >= EDGE_ON_THROUGH_OVER_SURFACE * n_surface)
        & (n_clear > 0.5 * n_edge_on)
    )
    for label in np.flatnonzero(cluster):
        members = involved[labels == label]
        cluster[label] = _thickness(points[members]) >= min_thickness or (
            _sheet_seen_through_inside(points[members], through[members], spacing[members])
        )
    answer = np.zeros(status.shape[0], dtype=bool)
    answer[involved] = cluster[labels]
    return answer


def _thickness(points: NDArray[np.float64]) -> float:
    """Standard deviation of ``points`` (shape (n, 3)) along their thinnest axis."""
    return float(np.sqrt(max(principal_axes(points)[1][0], 0.0)))


def _sheet_seen_through_inside(
    points: NDArray[np.float64], through: NDArray[np.bool_], spacing: NDArray[np.float64]
) -> bool:
    """Whether at least :data:`EDGE_ON_SEEN_THROUGH_FLOOR` of a sheet's points (shape (n, 3))
    lying more than :data:`SHEET_RIM_FACTOR` times their ``spacing`` (n,) inside its outline
    (the convex hull of the points in their plane) were seen ``through`` (n,); False for a
    sheet without such an interior (a strip, a line)."""
    from scipy.spatial import ConvexHull, QhullError  # on first use: API processes need no scipy

    centred, _, axes = principal_axes(points)
    in_plane = centred @ axes[:, 1:]
    try:
        hull = ConvexHull(in_plane)
    except QhullError:
        return False
    # each hull facet's equation is (unit outward normal, offset): -max is the depth inside
    depth = -(in_plane @ hull.equations[:, :2].T + hull.equations[:, 2]).max(axis=1)
    inside = depth > SHEET_RIM_FACTOR * spacing
    return bool(inside.any()) and bool(
        through[inside].sum() >= EDGE_ON_SEEN_THROUGH_FLOOR * inside.sum()
    )
