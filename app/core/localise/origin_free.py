"""The origin-free visibility test: no sensor origin and no stations, only the two surfaces.

Without a viewpoint, a change candidate (a point far from the other cloud's surface) is one of

- **a sampling gap** of the other cloud: the other epoch sampled the same surface around it,
  only sparsely (a floor or ceiling seen at grazing angles, the blind disc under or over a
  station of a merged survey);
- **unobserved**: the candidate lies on a plane that the other cloud has nearby but not here
  (a shadow: the other epoch saw the lit part of the wall or floor, not the part behind an
  occluder);
- **changed**: nothing of the other epoch lies on its plane anywhere near (a removed box's
  faces, an added box's faces).

Each candidate probes :data:`SECTORS` directions of its own tangent plane at distances that
double from its nearest-point distance (the other cloud's local gap) up to :data:`MAX_REACH`,
in both clouds: a *coplanar hit* is a point on the candidate's plane (within the tolerance,
with an agreeing normal) in that direction.  The neighbourhood adapts to the local spacing
(the probes start at the gap to the other cloud and grow from there), so a sparsely sampled
grazing surface is not mistaken for a missing one.

- In a sampling gap: the other cloud has coplanar hits in at least :data:`MIN_GAP_SECTORS`
  directions, and in every other direction the candidate's own surface ends too (an edge of
  the surface, e.g. a ceiling patch against a wall), before twice the gap.
- Unobserved: the other cloud has a coplanar hit in some direction.
- Changed: otherwise.

Then per cluster of candidates (within ``cluster_factor`` local spacings): a cluster most of
whose points lie on the other cloud's planes is a shadow or a gap, and the few changed points
in it (its rim, where the plane tolerance ran out) become unobserved
(:func:`settle_clusters`).  Last, a cluster of changed candidates must show that the other
epoch saw through it (:func:`behind_evidence`, :func:`keep_evidenced_clusters`): on the
normal lines of some of its points the other cloud has surface that this cloud lacks (the
floor under a removed box, the floor and wall behind an added one).  A face of an unchanged
object that the other epoch never saw has no such surface behind it: unobserved.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.localise.distance import Side
from app.core.localise.gaps import (
    NORMAL_AGREEMENT_COSINE,
    coplanar_near_probe,
    tangent_directions,
)
from app.core.localise.interface import VisibilityContext, VisibilityOutcome
from app.core.localise.rays import (
    STATUS_SEEN_THROUGH,
    STATUS_SURFACE,
    STATUS_UNOBSERVED,
    Candidates,
)
from app.core.localise.regions import cluster_labels
from app.core.localise.settings import GATHER_CHUNK
from app.core.localise.surface import LocalGeometry

__all__ = [
    "MAX_REACH",
    "SECTORS",
    "SurfaceTest",
    "behind_evidence",
    "keep_evidenced_clusters",
    "origin_free_status",
    "settle_clusters",
    "surface_test",
]

SECTORS = 8
"""Directions (45 degrees apart) probed in the candidate's tangent plane."""
SECTOR_HALF_ANGLE_COSINE = math.cos(math.radians(35.0))
"""A point counts for a direction within 35 degrees of it."""
PROBE_DOUBLINGS = 7
"""Probes at 1, 2, 4, ... 64 nearest-point distances in each direction (capped at MAX_REACH)."""
MAX_REACH = 4.0
"""Largest distance (metres) at which the other cloud's plane counts."""
SHADOW_REACH = 1.0
"""A candidate is on the other cloud's plane (a shadow, unobserved) when that plane is found
within this distance (metres) of it; farther, a coplanar face is a coincidence (another box's
face in line with a changed one), and the cluster and evidence steps decide."""
MIN_GAP_SECTORS = 4
"""A sampling gap has the other cloud's surface in at least half the directions."""
PROBE_NEIGHBOURS = 4
SETTLE_SHARE = 0.5
"""A cluster whose share of coplanar (gap or unobserved) candidates reaches this is not a
change: its changed points become unobserved."""
BEHIND_STEP_RATIO = 1.25
"""Probes along a candidate's normal, both ways, at distances growing by this ratio from
:data:`BEHIND_FIRST` to :data:`MAX_REACH`, look for the other cloud's unmatched points."""
BEHIND_FIRST = 0.05
BEHIND_RADIUS_FRACTION = 0.12
"""A point within this fraction of the probe's distance along the normal (at least
:data:`BEHIND_MIN_RADIUS`, at most :data:`BEHIND_MAX_RADIUS`) of the probe counts: above
(ratio - 1) / (ratio + 1) = 0.11 the probes' balls overlap, so no distance along the line is
missed, and the cone stays narrow (the floor beside a box's footprint is not under it)."""
BEHIND_MIN_RADIUS = 0.05
BEHIND_MAX_RADIUS = 0.3
UNMATCHED_FACTOR = 2.0
"""A point of the other cloud is unmatched when its nearest point in this cloud is farther
than this many of that point's spacings (and tau)."""
FOOTPRINT_MARGIN = 0.05
FOOTPRINT_HEIGHT = 0.3
FOOTPRINT_MIN_POINTS = 5
EVIDENCE_SHARE = 0.1
"""A cluster of changed candidates stays changed when this share of its points has the other
cloud's unmatched surface on its normal line; else it is unobserved (a face the other epoch
never saw)."""


def _plane_hits(
    query: NDArray[np.float64],
    unit: NDArray[np.float64],
    direction: NDArray[np.float64],
    reach: NDArray[np.float64],
    cloud: LocalGeometry,
    tolerance: float,
) -> NDArray[np.bool_]:
    """:func:`~app.core.localise.gaps.coplanar_near_probe` with this test's reach and cone."""
    return coplanar_near_probe(
        query,
        unit,
        direction,
        reach,
        cloud,
        tolerance,
        max_distance=MAX_REACH,
        half_angle_cosine=SECTOR_HALF_ANGLE_COSINE,
    )


def _probe(
    found: NDArray[np.bool_],
    todo: NDArray[np.bool_],
    query: NDArray[np.float64],
    unit: NDArray[np.float64],
    directions: NDArray[np.float64],
    reach: NDArray[np.float64],
    cloud: LocalGeometry,
    tolerance: float,
) -> None:
    """Set ``found[c, s]`` where ``todo[c, s]`` and ``cloud`` has a point on candidate c's
    plane near its probe in direction s at ``reach[c]`` (in place; shapes (c, S))."""
    rows, sectors = np.nonzero(todo)
    if rows.size == 0:
        return
    found[rows, sectors] = _plane_hits(
        query[rows], unit[rows], directions[rows, sectors], reach[rows], cloud, tolerance
    )


def origin_free_status(
    points: NDArray[np.float64],
    normal: NDArray[np.floating],
    nearest_distance: NDArray[np.float64],
    *,
    own: LocalGeometry,
    other: LocalGeometry,
    tolerance: float,
) -> NDArray[np.int8]:
    """Status of each candidate from the two clouds' surfaces alone.

    Parameters
    ----------
    points : ndarray, shape (c, 3)
        Change candidates of one cloud.
    normal : ndarray, shape (c, 3)
        Unit normal of each candidate's own surface.
    nearest_distance : ndarray, shape (c,)
        Distance of each candidate to its nearest point in the other cloud.
    own : LocalGeometry
        The candidates' cloud (its KD-tree, points and normals).
    other : LocalGeometry
        The other cloud.
    tolerance : float
        Largest offset (metres) from the candidate's plane, at the candidate: ``tau``.

    Returns
    -------
    ndarray, shape (c,), int8
        STATUS_SURFACE (a sampling gap of the other cloud: unchanged), STATUS_UNOBSERVED (on
        a plane the other cloud has nearby) or STATUS_SEEN_THROUGH (changed).
    """
    count = points.shape[0]
    status = np.full(count, STATUS_SEEN_THROUGH, dtype=np.int8)
    if count == 0:
        return status
    for start in range(0, count, GATHER_CHUNK):
        chunk = slice(start, start + GATHER_CHUNK)
        query = points[chunk]
        unit, directions = tangent_directions(normal[chunk], SECTORS)
        other_found = np.zeros((query.shape[0], SECTORS), dtype=bool)
        own_beyond = np.zeros((query.shape[0], SECTORS), dtype=bool)
        gap = np.maximum(nearest_distance[chunk], 1e-3)
        reaches = [
            np.minimum(gap * 2.0**doubling, MAX_REACH) for doubling in range(PROBE_DOUBLINGS)
        ]
        other_near = np.zeros((query.shape[0], SECTORS), dtype=bool)
        for doubling, reach in enumerate(reaches):
            # a reach capped at MAX_REACH repeats the last probe: skip it
            fresh = reach > reaches[doubling - 1] if doubling else np.ones_like(reach, bool)
            todo = ~other_found & fresh[:, None]
            _probe(other_found, todo, query, unit, directions, reach, other, tolerance)
            other_near |= other_found & (reach <= SHADOW_REACH)[:, None]
        # the own surface matters only where the other's might close a sampling gap
        possible_gap = other_found.sum(axis=1) >= MIN_GAP_SECTORS
        for doubling, reach in enumerate(reaches[1:], start=1):
            # own surface at twice the gap or farther: it continues in that direction
            fresh = reach > reaches[doubling - 1]
            todo = possible_gap[:, None] & ~other_found & ~own_beyond & fresh[:, None]
            _probe(own_beyond, todo, query, unit, directions, reach, own, tolerance)
        coplanar = other_near.any(axis=1)
        in_gap = (other_found.sum(axis=1) >= MIN_GAP_SECTORS) & (other_found | ~own_beyond).all(
            axis=1
        )
        status[chunk] = np.where(
            in_gap, STATUS_SURFACE, np.where(coplanar, STATUS_UNOBSERVED, STATUS_SEEN_THROUGH)
        )
    return status


def settle_clusters(
    points: NDArray[np.float64],
    *,
    spacing: NDArray[np.float64],
    status: NDArray[np.int8],
    cluster_factor: float,
) -> NDArray[np.int8]:
    """Changed candidates in clusters that mostly lie on the other cloud's planes (off its
    samples) become unobserved; sampling gaps (unchanged) link no cluster.

    Parameters
    ----------
    points : ndarray, shape (c, 3)
        The candidates.
    spacing : ndarray, shape (c,)
        Their cloud's local spacing.
    status : ndarray, shape (c,), int8
        From :func:`origin_free_status`.
    cluster_factor : float
        Candidates closer than this many local spacings are one cluster.

    Returns
    -------
    ndarray, shape (c,), int8
    """
    involved = np.flatnonzero(status != STATUS_SURFACE)  # gaps are unchanged: they link nothing
    if involved.size == 0:
        return status
    labels = cluster_labels(points[involved], cluster_factor * spacing[involved])
    coplanar_share = np.bincount(
        labels, weights=(status[involved] == STATUS_UNOBSERVED).astype(np.float64)
    ) / np.bincount(labels)
    settled = status.copy()
    settled[involved[coplanar_share[labels] >= SETTLE_SHARE]] = STATUS_UNOBSERVED
    return settled


def behind_evidence(
    points: NDArray[np.float64],
    normal: NDArray[np.floating],
    *,
    other_points: NDArray[np.float64],
    other_normal: NDArray[np.floating],
    other_unmatched: NDArray[np.bool_],
    min_radius: float = BEHIND_MIN_RADIUS,
    max_reach: float = MAX_REACH,
) -> NDArray[np.bool_]:
    """Whether the other cloud has surface that this one lacks behind each candidate.

    Looked for on the candidate's normal line (both ways: a surface parallel to the
    candidate's).  A removed box's top has the other epoch's floor below it, which this epoch
    could not see (the box hid it); an added box has the reference's floor and wall behind
    it (its side faces have the floor in their footprint: :func:`keep_evidenced_clusters`).
    A face of an unchanged object that the other epoch never saw has only surfaces both
    epochs share (or nothing) behind it.

    Parameters
    ----------
    points : ndarray, shape (c, 3)
    normal : ndarray, shape (c, 3)
    other_points : ndarray, shape (m, 3)
    other_normal : ndarray, shape (m, 3)
        Unit normals of the other cloud: its surface counts where parallel to the
        candidate's (a floor under a box top, a wall behind a box face).
    other_unmatched : ndarray, shape (m,), bool
        The other cloud's points with no point of this cloud near them.
    min_radius : float
        Smallest radius (metres) of a probe's ball (a sparse other cloud needs wider balls:
        about its spacing).
    max_reach : float
        Farthest probe (metres) along the normal line.

    Returns
    -------
    ndarray, shape (c,), bool
    """
    count = points.shape[0]
    found = np.zeros(count, dtype=bool)
    unmatched = other_points[other_unmatched]
    if count == 0 or unmatched.shape[0] == 0:
        return found
    unmatched_normal = other_normal[other_unmatched]
    tree = KDTree(unmatched)
    unit = normal.astype(np.float64)
    unit /= np.maximum(np.linalg.norm(unit, axis=1), 1e-12)[:, None]
    k = min(PROBE_NEIGHBOURS, unmatched.shape[0])
    steps = BEHIND_FIRST * BEHIND_STEP_RATIO ** np.arange(
        math.ceil(math.log(max_reach / BEHIND_FIRST, BEHIND_STEP_RATIO)) + 1
    )
    # along the normal both ways, a surface parallel to the candidate's
    lines = ((unit, unit), (-unit, unit))
    for step in steps:
        radius = min(max(min_radius, BEHIND_RADIUS_FRACTION * step), BEHIND_MAX_RADIUS)
        for direction, facing in lines:
            probes = points + step * direction
            distance, index = tree.query(probes, k=k, distance_upper_bound=radius)
            distance = np.asarray(distance).reshape(count, k)
            index = np.minimum(np.asarray(index).reshape(count, k), unmatched.shape[0] - 1)
            parallel = (
                np.abs(np.einsum("ckd,cd->ck", unmatched_normal[index], facing))
                >= NORMAL_AGREEMENT_COSINE
            )
            found |= ((distance <= radius) & parallel).any(axis=1)
    return found


def keep_evidenced_clusters(
    points: NDArray[np.float64],
    *,
    spacing: NDArray[np.float64],
    status: NDArray[np.int8],
    evidence: NDArray[np.bool_],
    cluster_factor: float,
    floor_points: NDArray[np.float64] | None = None,
) -> NDArray[np.int8]:
    """Changed clusters without enough :func:`behind_evidence` (nor floor in their
    footprint) become unobserved.

    Parameters
    ----------
    points : ndarray, shape (c, 3)
    spacing : ndarray, shape (c,)
    status : ndarray, shape (c,), int8
    evidence : ndarray, shape (c,), bool
    cluster_factor : float
    floor_points : ndarray, shape (f, 3), optional
        The other cloud's unmatched points on level surfaces (z up).  A cluster without
        enough evidence is still changed when :data:`FOOTPRINT_MIN_POINTS` of them lie in its
        footprint (its bounding box shrunk by :data:`FOOTPRINT_MARGIN`, near its lowest
        point): the floor under a removed box seen only from the side.  A single face has no
        footprint; the floor under an unchanged box was never seen.

    Returns
    -------
    ndarray, shape (c,), int8
    """
    changed = np.flatnonzero(status == STATUS_SEEN_THROUGH)
    if changed.size == 0:
        return status
    labels = cluster_labels(points[changed], cluster_factor * spacing[changed])
    share = np.bincount(labels, weights=evidence[changed].astype(np.float64)) / np.bincount(labels)
    evidenced = share >= EVIDENCE_SHARE
    if floor_points is not None and floor_points.shape[0]:
        for label in np.flatnonzero(~evidenced):
            cluster = points[changed[labels == label]]
            low = cluster.min(axis=0) + FOOTPRINT_MARGIN
            high = cluster.max(axis=0) - FOOTPRINT_MARGIN
            inside = (
                (floor_points[:, 0] > low[0])
                & (floor_points[:, 0] < high[0])
                & (floor_points[:, 1] > low[1])
                & (floor_points[:, 1] < high[1])
                & (np.abs(floor_points[:, 2] - cluster[:, 2].min()) <= FOOTPRINT_HEIGHT)
            )
            evidenced[label] = np.count_nonzero(inside) >= FOOTPRINT_MIN_POINTS
    kept = status.copy()
    kept[changed[~evidenced[labels]]] = STATUS_UNOBSERVED
    return kept


def surface_test(
    candidates: Candidates,
    *,
    own: Side,
    other: Side,
    threshold: float,
    cluster_factor: float,
) -> tuple[NDArray[np.int8], dict[str, Any]]:
    """The whole origin-free test of one cloud's candidates (the module's steps in order).

    Parameters
    ----------
    candidates : Candidates
        ``own``'s change candidates.
    own, other : Side
        The candidates' cloud and the other one (neither needs an origin).
    threshold : float
        ``tau``: the plane tolerance.
    cluster_factor : float
        Candidates closer than this many local spacings are one cluster.

    Returns
    -------
    status : ndarray, shape (c,), int8
        STATUS_SURFACE, STATUS_SEEN_THROUGH or STATUS_UNOBSERVED per candidate.
    counts : dict
        ``candidates_in_sampling_gaps``, ``candidates_on_other_planes`` (before the cluster
        steps) and ``candidates_without_evidence`` (changed clusters made unobserved).
    """
    status = origin_free_status(
        candidates.points,
        candidates.normal,
        own.nearest_distance[candidates.index],
        own=own.geometry,
        other=other.geometry,
        tolerance=threshold,
    )
    counts = {
        "candidates_in_sampling_gaps": int((status == STATUS_SURFACE).sum()),
        "candidates_on_other_planes": int((status == STATUS_UNOBSERVED).sum()),
    }
    status = settle_clusters(
        candidates.points, spacing=candidates.spacing, status=status, cluster_factor=cluster_factor
    )
    other_unmatched = other.nearest_distance > UNMATCHED_FACTOR * np.maximum(
        own.geometry.spacing[other.nearest_index], threshold
    )
    changed = status == STATUS_SEEN_THROUGH
    evidence = np.zeros(status.shape[0], dtype=bool)
    evidence[changed] = behind_evidence(
        candidates.points[changed],
        candidates.normal[changed],
        other_points=other.points,
        other_normal=other.geometry.normal,
        other_unmatched=other_unmatched,
    )
    level = np.abs(other.geometry.normal[:, 2]) >= NORMAL_AGREEMENT_COSINE
    status = keep_evidenced_clusters(
        candidates.points,
        spacing=candidates.spacing,
        status=status,
        evidence=evidence,
        cluster_factor=cluster_factor,
        floor_points=other.points[other_unmatched & level],
    )
    counts["candidates_without_evidence"] = int(
        np.count_nonzero(changed & (status == STATUS_UNOBSERVED))
    )
    return status, counts


class SurfaceTest:
    """The surface test as a visibility test (``name = "surfaces"``)."""

    name = "surfaces"

    def __call__(
        self, candidates: Candidates, *, own: Side, other: Side, context: VisibilityContext
    ) -> VisibilityOutcome:
        """:func:`surface_test` of ``own``'s candidates (changes need evidence behind them)."""
        status, counts = surface_test(
            candidates,
            own=own,
            other=other,
            threshold=context.threshold,
            cluster_factor=context.settings["cluster_factor"],
        )
        return VisibilityOutcome(
            status=status,
            confidence=np.ones(status.shape[0], dtype=np.float32),
            report=dict(counts),
        )
