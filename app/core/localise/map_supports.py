"""Feet of upright faces on the other epoch's supports: a band the change distance misjudges.

The change distance measures a point against the other cloud's samples (discs a support
factor of their spacing wide, :func:`~app.core.localise.distance.surface_distance`).  A sparse
map samples a floor, a desk top or a chair's seat in ring arcs 0.1-0.5 m apart, and never
under an object standing on it: the lowest few centimetres of an upright face (a box's sides,
a backrest above its seat) then lie farther than the change threshold from every sample,
although the support they stand on runs under them, within the threshold, in the other
epoch's world as in this one's.  Whatever happened to the object, that band is no change of
its own: a removed box's foot stood on a floor the other epoch still has, an added one's
stands on the floor the other epoch saw.

A candidate on an upright face (its normal's vertical component under
:data:`~app.core.localise.map_parts.UPRIGHT_NORMAL_Z`) rests on the other epoch's support when,
among the other cloud's :data:`SUPPORT_NEIGHBOURS` nearest points within
:data:`SUPPORT_REACH` of it, at least :data:`MIN_SUPPORT_SAMPLES` are level (normals within 30
degrees of vertical) and lie, within the plane tolerance, at one height (their median) that
is less than the change threshold under the candidate, and no more than the tolerance over
it.  Its status is then surface (unchanged), in the map test and in the trajectory test
(:mod:`~app.core.localise.trajectory_visibility`: the ray test sees through the foot's place
like the rest of the face, yet the band is no change of its own there either).  The samples
may lie on one side only: a seat seen in front of a backrest, a desk top seen beside a box.
Lines (a single ring arc, its fitted normal arbitrary) and upright surfaces count for
nothing.  Level candidates are left to the sampling-gap probe
(:func:`~app.core.localise.map_planes.in_sampling_gap`): a removed box's top level with a desk
top beside it is a change.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.localise.distance import Side
from app.core.localise.gaps import NORMAL_AGREEMENT_COSINE
from app.core.localise.map_parts import UPRIGHT_NORMAL_Z
from app.core.localise.rays import (
    STATUS_SEEN_THROUGH,
    STATUS_SURFACE,
    STATUS_UNOBSERVED,
    Candidates,
)
from app.core.localise.regions import EVIDENCE_NO_COVERAGE, EVIDENCE_SEEN_EMPTY
from app.core.localise.settings import GATHER_CHUNK
from app.core.localise.surface import LocalGeometry

__all__ = [
    "MIN_SUPPORT_SAMPLES",
    "SUPPORT_NEIGHBOURS",
    "SUPPORT_REACH",
    "map_statuses",
    "part_bottom",
    "resting_on_support",
]

SUPPORT_REACH = 0.5
"""Metres: the other epoch's level samples within this distance of the candidate count (a
box's side stands 0.25-0.5 m from the floor samples round its footprint)."""
SUPPORT_NEIGHBOURS = 32
MIN_SUPPORT_SAMPLES = 6
"""Level samples of the other cloud at the support's height (as for a sampling gap)."""


def resting_on_support(
    points: NDArray[np.float64],
    normal: NDArray[np.floating],
    part_bottom: NDArray[np.float64],
    other: LocalGeometry,
    tolerance: float,
    change_threshold: float,
    samples: NDArray[np.bool_] | None = None,
) -> NDArray[np.bool_]:
    """Whether each candidate is on an upright face within ``change_threshold`` above a level
    support the other epoch sampled near it (shapes (c, 3), (c, 3) -> (c,)).

    Parameters
    ----------
    points : ndarray, shape (c, 3)
        The candidates.
    normal : ndarray, shape (c, 3)
        Their normals.
    part_bottom : ndarray, shape (c,)
        The height of the lowest candidate of each candidate's surface part: a face standing
        on the support ends at it, one reaching lower passes it by.
    other : LocalGeometry
        The other epoch's cloud.
    tolerance : float
        ``tau``: the plane tolerance (metres).
    change_threshold : float
        ``c`` (metres).
    samples : ndarray, shape (n,), bool, optional
        Which of ``other``'s n points may be support samples (default: all).

    Returns
    -------
    ndarray, shape (c,), bool
    """
    resting = np.zeros(points.shape[0], dtype=bool)
    upright = np.flatnonzero(np.abs(normal[:, 2]) < UPRIGHT_NORMAL_Z)
    sample_points, tree = other.points, other.tree
    level = (np.abs(other.normal[:, 2]) >= NORMAL_AGREEMENT_COSINE) & ~other.linear
    if samples is not None:  # only the level samples allowed, in a tree of their own
        sample_points = other.points[level & samples]
        level = np.ones(sample_points.shape[0], dtype=bool)
        tree = KDTree(sample_points) if sample_points.shape[0] else None
    k = min(SUPPORT_NEIGHBOURS, sample_points.shape[0])
    if upright.size == 0 or k < MIN_SUPPORT_SAMPLES or tree is None:
        return resting
    for start in range(0, upright.shape[0], GATHER_CHUNK):
        chosen = upright[start : start + GATHER_CHUNK]
        height = points[chosen, 2]
        distance, index = tree.query(points[chosen], k=k, distance_upper_bound=SUPPORT_REACH)
        distance = np.asarray(distance).reshape(chosen.shape[0], k)
        index = np.minimum(
            np.asarray(index).reshape(chosen.shape[0], k), sample_points.shape[0] - 1
        )
        sample_height = sample_points[index, 2]
        below = height[:, None] - sample_height
        usable = (
            (distance <= SUPPORT_REACH)
            & level[index]
            & (below >= -tolerance)
            & (below < change_threshold)
        )
        enough = usable.sum(axis=1) >= MIN_SUPPORT_SAMPLES
        if not enough.any():
            continue
        rows = np.flatnonzero(enough)
        support = np.nanmedian(np.where(usable[rows], sample_height[rows], np.nan), axis=1)
        on_support = usable[rows] & (np.abs(sample_height[rows] - support[:, None]) <= tolerance)
        rise = height[rows] - support
        resting[chosen[rows]] = (
            (on_support.sum(axis=1) >= MIN_SUPPORT_SAMPLES)
            & (rise < change_threshold)
            & (rise >= -tolerance)
            & (part_bottom[chosen[rows]] >= support - tolerance)
        )
    return resting


def part_bottom(points: NDArray[np.float64], labels: NDArray[np.int64]) -> NDArray[np.float64]:
    """The height of the lowest point of each point's part (``labels``, shape (c,); points
    shape (c, 3)), shape (c,)."""
    if labels.size == 0:
        return np.zeros(0)
    bottom = np.full(int(labels.max()) + 1, np.inf)
    np.minimum.at(bottom, labels, points[:, 2])
    return bottom[labels]


def map_statuses(
    candidates: Candidates,
    labels: NDArray[np.int64],
    covered: NDArray[np.bool_],
    other: Side,
    threshold: float,
    change_threshold: float,
) -> tuple[NDArray[np.int8], NDArray[np.int8], int]:
    """Each candidate's status and evidence (shape (c,), int8) from the parts' verdicts
    (``covered``: in a coverage difference, shape (c,), bool), and how many rest on the other
    epoch's support (:func:`resting_on_support`: surface)."""
    status = np.where(covered, STATUS_UNOBSERVED, STATUS_SEEN_THROUGH).astype(np.int8)
    evidence = np.where(covered, EVIDENCE_NO_COVERAGE, EVIDENCE_SEEN_EMPTY).astype(np.int8)
    resting = resting_on_support(
        candidates.points,
        candidates.normal,
        part_bottom(candidates.points, labels),
        other.geometry,
        threshold,
        change_threshold,
    )
    status[resting] = STATUS_SURFACE
    return status, evidence, int(resting.sum())
