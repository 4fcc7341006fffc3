"""Level parts the other epoch saw along their rims only: a desk top seen as ring arcs.

A sparse map (a robot's 16-ring lidar passing a desk) may sample a desk top only where a ring
arc crosses its front rim, its ends, or once across it, and the wall behind it: the top itself
lies between those samples.  The rim arcs are lines (no normal: they carry on no plane, and a
line never counts as surface extending along a plane, :mod:`~app.core.localise.sample_lines`),
the floor under an open desk is seen, so the top is no unseen top either, and the other epoch's
nearest samples around it are the wall's, so it lies in no sampling gap of
:func:`~app.core.localise.map_planes.in_sampling_gap` (32 nearest within 0.5 m, mostly off
its plane).  It was read as a change (robot office 1202: a 1.4 x 0.56 m desk top, 165 false
points).

Here the other epoch's samples are gathered on the part's level plane itself (within ``tau``
plus :data:`~app.core.localise.gaps.PLANE_SLOPE` a metre of each point's height,
:data:`RIM_REACH` around it): a point lies inside a rim when they hold no empty half-plane
around it (:data:`RIM_MIN_POINTS` at least) and one of them is a level edge, a level sample or
a level line (a rim arc), not only walls meeting the plane.  A level part is a coverage
difference when :data:`~app.core.localise.map_verdict.GAP_SHARE` of its probed points do.
A removed or added object's top has no samples of the other epoch at its height around it
(the floor lies under it; walls meet its plane on one or two sides: a box in a corner has no
level edge); a slid seat has the other seat on one side only.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from app.core.localise.gaps import NORMAL_AGREEMENT_COSINE, PLANE_SLOPE
from app.core.localise.map_planes import widest_empty_angle
from app.core.localise.sample_lines import IN_PLANE_SINE, sample_lines
from app.core.localise.surface import LocalGeometry

__all__ = ["RIM_MIN_POINTS", "RIM_REACH", "RIM_SAMPLE", "inside_rims", "rim_gap_share"]

RIM_REACH = 0.5
"""Metres (horizontal) around a point in which the other epoch's samples on its level plane
tell whether it lies inside their rim."""
RIM_MIN_POINTS = 6
"""Fewer of the other epoch's samples on the plane around a point than this say nothing."""
RIM_SAMPLE = 64
"""Points probed per part, spread over it."""
RIM_MAX_GATHER = 20000
"""At most this many of the other epoch's samples are gathered per part (spread evenly)."""


def _level_edges(other: LocalGeometry, index: NDArray[np.int64]) -> NDArray[np.bool_]:
    """Whether each of ``other``'s samples ``index`` (shape (m,)) is a level sample or lies on
    a level line (a rim arc), not on an upright surface (shape (m,), bool)."""
    on_line, direction = sample_lines(other, index)
    level_line = on_line & (np.abs(direction[:, 2]) <= IN_PLANE_SINE)
    level = (np.abs(other.normal[index, 2]) >= NORMAL_AGREEMENT_COSINE) & ~other.linear[index]
    return np.where(on_line, level_line, level)


def inside_rims(
    points: NDArray[np.float64],
    other: LocalGeometry,
    tolerance: float,
    by_height: NDArray[np.int64],
) -> NDArray[np.bool_]:
    """Whether each point of one level part lies inside the other epoch's rim on its plane
    (shape (p, 3) -> (p,)).

    Parameters
    ----------
    points : ndarray, shape (p, 3)
        The part's probed points.
    other : LocalGeometry
        The other epoch's cloud.
    tolerance : float
        ``tau``, the plane tolerance (metres).
    by_height : ndarray, shape (n,), int64
        ``other``'s points ordered by height (``argsort`` of their z).
    """
    band = tolerance + PLANE_SLOPE * RIM_REACH
    heights = other.points[by_height, 2]
    start, stop = np.searchsorted(
        heights, [points[:, 2].min() - band, points[:, 2].max() + band], side="left"
    )
    slab = by_height[start:stop]
    low, high = points[:, :2].min(axis=0) - RIM_REACH, points[:, :2].max(axis=0) + RIM_REACH
    slab = slab[np.all((other.points[slab, :2] >= low) & (other.points[slab, :2] <= high), axis=1)]
    if slab.shape[0] > RIM_MAX_GATHER:
        slab = slab[np.linspace(0, slab.shape[0] - 1, RIM_MAX_GATHER).round().astype(np.int64)]
    if slab.shape[0] < RIM_MIN_POINTS:
        return np.zeros(points.shape[0], dtype=bool)
    offset = other.points[slab][None, :, :] - points[:, None, :]
    across = np.hypot(offset[:, :, 0], offset[:, :, 1])
    held = (across <= RIM_REACH) & (np.abs(offset[:, :, 2]) <= tolerance + PLANE_SLOPE * across)
    used = np.flatnonzero(held.any(axis=0))
    if used.shape[0] < RIM_MIN_POINTS:  # too few around any point to hold a rim
        return np.zeros(points.shape[0], dtype=bool)
    held, offset = held[:, used], offset[:, used, :]
    edge = _level_edges(other, slab[used])
    angle = np.arctan2(offset[:, :, 1], offset[:, :, 0])
    return (
        (held.sum(axis=1) >= RIM_MIN_POINTS)
        & (held & edge[None, :]).any(axis=1)
        & (widest_empty_angle(angle, held) <= math.pi)
    )


def rim_gap_share(
    points: NDArray[np.float64],
    normal: NDArray[np.floating],
    labels: NDArray[np.int64],
    recheck: NDArray[np.bool_],
    *,
    own: LocalGeometry,
    other: LocalGeometry,
    tolerance: float,
) -> NDArray[np.float64]:
    """Per level part marked in ``recheck`` (0 elsewhere), the share of its (up to
    :data:`RIM_SAMPLE`) probed points inside the other epoch's rim on its plane
    (:func:`inside_rims`).

    Parameters
    ----------
    points, normal : ndarray, shape (c, 3)
        The candidates and their normals.
    labels : ndarray, shape (c,), int64
        Their surface parts.
    recheck : ndarray, shape (parts,), bool
    own, other : LocalGeometry
        This epoch's cloud (unused: the signature of
        :func:`~app.core.localise.map_lines.line_gap_share`) and the other epoch's.
    tolerance : float
        ``tau``, the plane tolerance (metres).

    Returns
    -------
    ndarray, shape (parts,), float64
    """
    share = np.zeros(recheck.shape[0])
    sizes = np.bincount(labels, minlength=recheck.shape[0])
    vertical = np.bincount(
        labels, weights=np.abs(normal[:, 2]).astype(np.float64), minlength=recheck.shape[0]
    ) / np.maximum(sizes, 1)
    level = recheck & (vertical >= NORMAL_AGREEMENT_COSINE)
    if not level.any() or other.points.shape[0] < RIM_MIN_POINTS:
        return share
    by_height = np.argsort(other.points[:, 2], kind="stable")
    for part in np.flatnonzero(level):
        members = np.flatnonzero(labels == part)
        if members.shape[0] > RIM_SAMPLE:
            members = members[np.linspace(0, members.shape[0] - 1, RIM_SAMPLE).round().astype(int)]
        share[part] = inside_rims(points[members], other, tolerance, by_height).mean()
    return share
