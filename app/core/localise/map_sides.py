"""Which side of a surface part its own epoch saw it from, told by the other epoch's surface
behind it.

A surface seen in a fused map was seen from one side, its open side; the map test's
see-through probes take the other epoch's surface on a candidate's normal line, surface this
epoch lacks, as what lay behind the candidate (the floor under a removed chair, the wall behind
a removed board, an object's far face).  Surface in front of it, on the open side, this epoch's
path would have seen itself: it looked at the part through that air.  So the side of a part
where the other epoch's lacking surface lies along the normal lines of most of its candidates
is its inner side (:func:`inner_sides`), measured in each cloud's own spacing: no sensor
position.  Other epoch's samples this epoch lacks that stand in front of the part, off its
plane on the open side, are in the air this epoch saw through (:func:`in_front`): no surface
the part's object hid from this epoch (a fan of the other path's flying pixels behind its
view of the object's rim, fused from many frames, RGB-D room 504 of ``bench.moving_maps``).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.localise.distance import Side
from app.core.localise.gaps import NORMAL_AGREEMENT_COSINE
from app.core.localise.origin_free import (
    BEHIND_FIRST,
    BEHIND_MAX_RADIUS,
    BEHIND_MIN_RADIUS,
    BEHIND_RADIUS_FRACTION,
    BEHIND_STEP_RATIO,
    behind_evidence,
)

__all__ = [
    "INNER_MAJORITY",
    "INNER_MIN",
    "INNER_PROBES",
    "SEE_THROUGH_REACH",
    "SPARSE_PROBE_FACTOR",
    "in_front",
    "inner_sides",
    "near_candidates",
    "nearest_in_air",
    "oriented_depths",
    "part_axes",
    "surface_behind",
]

SEE_THROUGH_REACH = 1.2
"""Farther along the normal line, the other epoch's unmatched surface is as likely another
coverage difference (the ceiling a path saw above a floor patch the other path saw) as what
stood in front of or behind the cluster."""
SPARSE_PROBE_FACTOR = 1.5
"""The see-through probes' balls are at least this many of the other cloud's median spacings
wide (a sparse cloud's surface is found between its samples)."""
PROBE_NEIGHBOURS = 4
INNER_PROBES = 128
"""Candidates of a part (spread through it) whose normal lines are probed for its inner side."""
INNER_MAJORITY = 2.0
"""A part's inner side is known when its candidates find the other epoch's surface behind them
on one side at least this many times as often as on the other (and on at least a tenth)."""
INNER_MIN = 10
"""Fewer candidates (of a part's level or upright ones) than this tell no side."""
LEVEL_NORMAL_Z = math.sqrt(0.5)
"""Candidates whose normals are closer to vertical than 45 degrees are level (surfaces), the
others upright: a part's level and upright candidates (a box's top and side in one part) are
oriented apart here, and are not in one surface part where a part has much of both
(``map_parts.MIXED_SHARE``, ``map_parts.surface_parts``)."""


def part_axes(
    normal: NDArray[np.floating], labels: NDArray[np.int64], n_parts: int
) -> NDArray[np.float64]:
    """Per part, the principal direction of its candidates' (unsigned) normals, shape (parts, 3)."""
    unit = normal.astype(np.float64)
    unit /= np.maximum(np.linalg.norm(unit, axis=1), 1e-12)[:, None]
    scatter = np.zeros((n_parts, 3, 3))
    np.add.at(scatter, labels, unit[:, :, None] * unit[:, None, :])
    _, vectors = np.linalg.eigh(scatter + 1e-12 * np.eye(3))
    return vectors[:, :, 2]


def oriented_depths(
    points: NDArray[np.float64],
    unit: NDArray[np.float64],
    other: Side,
    counted: NDArray[np.bool_],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """How far along ``+unit`` and ``-unit`` each point has the other cloud's ``counted``
    surface parallel to its own (within :data:`SEE_THROUGH_REACH`).

    The probes are those of :func:`~app.core.localise.origin_free.behind_evidence` (balls
    growing with the distance, at least :data:`SPARSE_PROBE_FACTOR` of the other cloud's
    median spacing wide), each way on its own.

    Parameters
    ----------
    points : ndarray, shape (c, 3)
    unit : ndarray, shape (c, 3)
        Unit normals, oriented.
    other : Side
    counted : ndarray, shape (m,), bool
        The other cloud's points that count.

    Returns
    -------
    ahead, back : ndarray, shape (c,)
        The nearest such surface's distance along ``+unit`` and ``-unit`` (inf: none).
    """
    count = points.shape[0]
    ahead = np.full(count, np.inf)
    back = np.full(count, np.inf)
    chosen = np.flatnonzero(counted)
    if count == 0 or chosen.shape[0] == 0:
        return ahead, back
    tree = KDTree(other.points[chosen])
    chosen_normal = other.geometry.normal[chosen]
    min_radius = max(
        BEHIND_MIN_RADIUS, SPARSE_PROBE_FACTOR * float(np.median(other.geometry.spacing))
    )
    k = min(PROBE_NEIGHBOURS, chosen.shape[0])
    steps = BEHIND_FIRST * BEHIND_STEP_RATIO ** np.arange(
        math.ceil(math.log(SEE_THROUGH_REACH / BEHIND_FIRST, BEHIND_STEP_RATIO)) + 1
    )
    for step in steps:
        radius = min(max(min_radius, BEHIND_RADIUS_FRACTION * step), BEHIND_MAX_RADIUS)
        for sign, depth in ((1.0, ahead), (-1.0, back)):
            todo = np.flatnonzero(np.isinf(depth))
            if todo.shape[0] == 0:
                continue
            distance, index = tree.query(
                points[todo] + sign * step * unit[todo], k=k, distance_upper_bound=radius
            )
            distance = np.asarray(distance).reshape(todo.shape[0], k)
            index = np.minimum(np.asarray(index).reshape(todo.shape[0], k), chosen.shape[0] - 1)
            parallel = (
                np.abs(np.einsum("ckd,cd->ck", chosen_normal[index], unit[todo]))
                >= NORMAL_AGREEMENT_COSINE
            )
            found = ((distance <= radius) & parallel).any(axis=1)
            depth[todo[found]] = step
    return ahead, back


def inner_sides(
    points: NDArray[np.float64],
    normal: NDArray[np.floating],
    labels: NDArray[np.int64],
    wanted: NDArray[np.bool_],
    other: Side,
    counted: NDArray[np.bool_],
) -> NDArray[np.float64]:
    """Per candidate of the ``wanted`` parts, the unit directions into its part's inner sides,
    of its upright and of its level candidates (a box's side and top in one part): the side
    where the other epoch's ``counted`` surface lies behind most of their probed candidates
    (:data:`INNER_PROBES` of them, :data:`INNER_MAJORITY`); zero where not known.

    Parameters
    ----------
    points, normal : ndarray, shape (c, 3)
        The candidates and their normals.
    labels : ndarray, shape (c,), int64
        Their surface parts.
    wanted : ndarray, shape (parts,), bool
    other : Side
    counted : ndarray, shape (m,), bool
        The other cloud's points this epoch lacks.

    Returns
    -------
    ndarray, shape (c, 2, 3), float64
        Into the inner side of the part's upright candidates, then of its level ones.
    """
    inward = np.zeros((points.shape[0], 2, 3), dtype=np.float64)
    # a box's top and side in one part each have their own inner side
    groups = 2 * labels + (np.abs(normal[:, 2]) >= LEVEL_NORMAL_Z)
    n_groups = 2 * wanted.shape[0]
    chosen = np.flatnonzero(wanted[labels])
    if chosen.shape[0] == 0:
        return inward
    axes = part_axes(normal[chosen], groups[chosen], n_groups)
    # up to INNER_PROBES candidates a group, spread through it (every n-th in cloud order)
    order = chosen[np.argsort(groups[chosen], kind="stable")]
    sizes = np.bincount(groups[order], minlength=n_groups)
    rank = np.arange(order.shape[0]) - np.repeat(np.cumsum(sizes) - sizes, sizes)
    stride = np.maximum(1, np.ceil(sizes / INNER_PROBES)).astype(np.int64)
    probe = order[rank % stride[groups[order]] == 0]
    ahead, back = oriented_depths(points[probe], axes[groups[probe]], other, counted)
    probed = np.bincount(groups[probe], minlength=n_groups).astype(np.float64)
    hits_ahead = np.bincount(groups[probe], weights=np.isfinite(ahead), minlength=n_groups)
    hits_back = np.bincount(groups[probe], weights=np.isfinite(back), minlength=n_groups)
    enough = (probed >= INNER_MIN) & (np.maximum(hits_ahead, hits_back) >= 0.1 * probed)
    sign = np.where(
        enough & (hits_ahead >= INNER_MAJORITY * hits_back),
        1.0,
        np.where(enough & (hits_back >= INNER_MAJORITY * hits_ahead), -1.0, 0.0),
    )
    oriented = sign[:, None] * axes
    inward[chosen, 0] = oriented[2 * labels[chosen]]
    inward[chosen, 1] = oriented[2 * labels[chosen] + 1]
    return inward


def in_front(
    offset: NDArray[np.float64], inward: NDArray[np.float64], tolerance: float
) -> NDArray[np.bool_]:
    """Whether each offset (from a candidate to a sample of the other epoch, shape (b, 3))
    leads more than ``tolerance`` out of the candidate's part on an open side (``inward``,
    shape (b, 2, 3): :func:`inner_sides`, zero where not known: never), shape (b,).  Either
    side of a box's face and top counts: the sample stands outside the box, over its top or
    in front of its face (a candidate on the rim between them has a normal half-way)."""
    return (np.einsum("bd,bsd->bs", offset, inward) < -tolerance).any(axis=1)


def surface_behind(
    points: NDArray[np.float64],
    normal: NDArray[np.floating],
    other: Side,
    counted: NDArray[np.bool_],
) -> NDArray[np.bool_]:
    """Whether the other cloud's ``counted`` points lie on each point's normal line within
    :data:`SEE_THROUGH_REACH` (:func:`~app.core.localise.origin_free.behind_evidence`, with
    probes at least :data:`SPARSE_PROBE_FACTOR` of its spacings wide); shapes (c, 3) -> (c,)."""
    return behind_evidence(
        points,
        normal,
        other_points=other.points,
        other_normal=other.geometry.normal,
        other_unmatched=counted,
        max_reach=SEE_THROUGH_REACH,
        min_radius=max(
            BEHIND_MIN_RADIUS, SPARSE_PROBE_FACTOR * float(np.median(other.geometry.spacing))
        ),
    )


def near_candidates(
    points: NDArray[np.float64], other: Side, other_unmatched: NDArray[np.bool_]
) -> NDArray[np.int64]:
    """Indices of the other cloud's unmatched points that the see-through probes from
    ``points`` (shape (c, 3)) can reach (within :data:`SEE_THROUGH_REACH` plus a probe)."""
    unmatched = np.flatnonzero(other_unmatched)
    if unmatched.shape[0] == 0 or points.shape[0] == 0:
        return unmatched[:0]
    reach = SEE_THROUGH_REACH + BEHIND_MAX_RADIUS
    distance, _ = KDTree(points).query(other.points[unmatched], k=1, distance_upper_bound=reach)
    return unmatched[np.asarray(distance).ravel() <= reach]


def nearest_in_air(
    points: NDArray[np.float64],
    inward: NDArray[np.float64],
    other: Side,
    counted: NDArray[np.bool_],
    tolerance: float,
) -> NDArray[np.bool_]:
    """Whether each point's nearest sample of the other epoch is one of its ``counted`` (those
    this epoch lacks) standing in front of the point's part (:func:`in_front`); shapes (b, 3),
    (b, 2, 3) -> (b,)."""
    if points.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    _, nearest = other.geometry.tree.query(points, k=1)
    nearest = np.asarray(nearest).ravel()
    return counted[nearest] & in_front(other.points[nearest] - points, inward, tolerance)
