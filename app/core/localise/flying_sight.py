"""Isolated samples on lines of sight past an own edge: flying pixels the passes kept.

A depth camera's flying pixel lies on its pixel's line of sight between a near surface's edge and
the surface behind it: from the pixel towards the camera the line grazes the near surface's
edge and then runs through the open room to the camera; away from the camera it meets the
surface behind.  A fused map keeps no camera position, but the open room tells where a camera
could have been: a sample with :data:`SIGHT_LINES` directions along which (i) an own sample
lies close to the line a little in front (the edge), (ii) past that edge both maps leave the
line empty up to :data:`CLEAR_REACH` (a camera could see along it) and (iii) an own sample lies
on the line behind it, is where a flying pixel would be.

Two kinds of isolated samples that the flying passes keep are tested.  Scattered ones that
:data:`~app.core.localise.flying_samples.OTHER_NEAR` keeps (a sample of the other map within one
median spacing): a turned chair's old surface under the other map's flying pixels (drifting
RGB-D rooms 503 / 303: 2 + 9 such pixels kept 45 / 308 of the chair's points unchanged) holds
them as a thin part both maps saw would (s27).  And flat ones the other map does not hold
(s28): a flying pixel alone in the air has a far surface's samples for its 10 neighbours, flat
at k, so no scatter; 3 such reference pixels held 27 of room 503's 78 scored points of the
turned chair within the change distance (63 % found; taken, 78 %).  A flat isolated sample the
other map holds stays (a thin part both saw: clean room 104's chair leg).  A thin part seen
past an edge with a wall behind it can look the same along a few lines (a real sample just
behind a silhouette); such samples have fewer lines of sight than a fan behind a long edge,
hence the count.  The lines' width and where the edge may start follow the map's median
spacing; how far a camera stands and how far a flying pixel lies from its edge are metres.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

__all__ = [
    "CLEAR_REACH",
    "DIRECTIONS",
    "EDGE_REACH",
    "EDGE_START",
    "NEAR_LINE",
    "SIGHT_LINES",
    "on_sight_lines",
]

DIRECTIONS = 600
"""Directions tried per candidate (a Fibonacci sphere, ~8 degrees apart)."""
NEAR_LINE = 0.5
"""Median spacings of the map: a sample this close to a point of a line lies on it (1 cm on the
RGB-D rooms' 1.9-2.2 cm), also the step along a line; the space past the edge is empty when no
sample of either map lies within 1.5 times this of the line.  A map thinned to 5 mm voxels has
its samples, and its flying pixels' neighbours, four times closer: the lines narrow with it."""
SIGHT_LINES = 10
"""Directions (of :data:`DIRECTIONS`) a flying candidate lies on a line of sight along: a flying
pixel behind a long edge (a rim, a chair's back) lies on such lines from a spread of places a
camera could stand; a real sample seen just past an edge from a few.  Among the candidates the
other map held in drifting RGB-D rooms 100 / 104 / 303 / 503 (truth: > 5 cm from their
surface), at least 1 line: 43 of 45 flying, 60 of 90 solid; at least 10: 37 / 23; (at least
1 took 29 reference samples of room 100's sparse wall band: 437 scan points changed)."""
EDGE_REACH = 0.8
"""Metres: the near edge lies at most this far in front of a flying pixel (its depth mixed with
a surface up to ~1 m in front of the one behind)."""
CLEAR_REACH = 1.2
"""Metres from the candidate: the line past the edge is empty of both maps' samples up to here
(a handheld camera's nearest surfaces are 0.5-1 m away); also how far behind the candidate the
surface behind may lie."""
EDGE_START = 0.75
"""Median spacings in front of the candidate where the edge may start (its own neighbours are
nearer; 1.5 cm on the RGB-D rooms)."""
DIRECTION_SETS = 4
"""The directions are tried in this many interleaved sets (each spread over the sphere, ~16
degrees apart), the count stopping once it reaches :data:`SIGHT_LINES` (most flying pixels
reach it in the first set)."""
EMPTY_SETS = 2
"""A sample with no line of sight in the first this many sets (300 directions, ~11 degrees
apart) is not tried further: a fan behind an edge is seen along a cone of lines tens of degrees
wide.  Drifting RGB-D room 100: 782 of the 1,277 samples tried have none there, none of them
10 in all 600; after one set (150 directions) 8 of drifting room 503's scan flying pixels were
lost (a 147-point false region)."""
BEHIND_START = 0.03
"""Metres behind the candidate where the surface behind may start."""


def _sphere(count: int) -> NDArray[np.float64]:
    """``count`` unit vectors spread evenly over the sphere (Fibonacci), shape (count, 3)."""
    rank = np.arange(count) + 0.5
    polar = np.arccos(1.0 - 2.0 * rank / count)
    azimuth = math.pi * (1.0 + math.sqrt(5.0)) * rank
    return np.column_stack(
        [np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)]
    )


def _near(tree: KDTree, points: NDArray[np.float64], radius: float) -> NDArray[np.bool_]:
    """Whether a sample of ``tree`` lies within ``radius`` of each of ``points`` (shape
    (..., 3)), shape (...)."""
    flat = np.ascontiguousarray(points.reshape(-1, 3))
    distance = tree.query(flat, k=1, distance_upper_bound=radius)[0]
    return np.isfinite(distance).reshape(points.shape[:-1])


def _open_lines(
    candidate: NDArray[np.float64],
    own: KDTree,
    both: KDTree,
    along: NDArray[np.float64],
    directions: NDArray[np.float64],
) -> int:
    """How many of ``directions`` (unit, shape (d, 3)) one candidate (shape (3,)) lies on a
    line of sight along: an own run of samples starts within :data:`EDGE_REACH` in front (the
    edge), both maps leave the line empty past it up to :data:`CLEAR_REACH`, and an own sample
    lies behind it; ``along``: the steps along each line, metres, one line width apart from one
    line width on (:data:`NEAR_LINE` median spacings).  Both maps' samples are looked for past
    the edge only on the lines that have one."""
    width = float(along[0])
    towards = candidate - directions[:, None, :] * along[None, :, None]
    reach = int(np.searchsorted(along, EDGE_REACH, side="right")) + 1  # an edge ends in here
    hit = _near(own, towards[:, :reach], width)
    index = np.arange(along.size)
    front = hit & (along[:reach] >= EDGE_START / NEAR_LINE * width)
    begin = np.where(front.any(axis=1), front.argmax(axis=1), reach)
    past = ~hit & (index[:reach] > begin[:, None])
    after = np.where(past.any(axis=1), past.argmax(axis=1), reach)
    last = along[np.clip(after - 1, 0, along.size - 1)]
    edged = np.flatnonzero((begin < reach) & (last <= EDGE_REACH) & (after + 2 < along.size))
    if edged.size == 0:
        return 0
    beyond = index[None, :] >= after[edged][:, None] + 2
    blocked = np.zeros(beyond.shape, dtype=bool)
    blocked[beyond] = _near(both, towards[edged][beyond], 1.5 * width)
    open_line = edged[~blocked.any(axis=1)]
    if open_line.size == 0:
        return 0
    behind = candidate + directions[open_line][:, None, :] * along[None, :, None]
    return int((_near(own, behind, width) & (along >= BEHIND_START)).any(axis=1).sum())


def _sighted(
    candidate: NDArray[np.float64],
    own: KDTree,
    both: KDTree,
    along: NDArray[np.float64],
    directions: NDArray[np.float64],
) -> bool:
    """Whether one candidate (shape (3,)) lies on lines of sight (:func:`_open_lines`) along
    :data:`SIGHT_LINES` of ``directions`` (shape (d, 3)): counted a spread share of them at a
    time (:data:`DIRECTION_SETS` interleaved sets), stopping once they are reached, or when the
    first :data:`EMPTY_SETS` sets hold none."""
    found = 0
    for first in range(DIRECTION_SETS):
        found += _open_lines(candidate, own, both, along, directions[first::DIRECTION_SETS])
        if found >= SIGHT_LINES:
            return True
        if found == 0 and first + 1 == EMPTY_SETS:
            return False
    return False


def on_sight_lines(
    points: NDArray[np.float64],
    candidates: NDArray[np.intp],
    solid: NDArray[np.bool_],
    other_points: NDArray[np.float64],
    spacing: float,
) -> NDArray[np.bool_]:
    """Which ``candidates`` lie on a line of sight past an own edge (module docstring).

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        One map's samples.
    candidates : ndarray, shape (m,), int
        Indices into ``points`` of the samples to test.
    solid : ndarray, shape (n,), bool
        The samples of ``points`` that count as surface (not flying candidates).
    other_points : ndarray, shape (p, 3)
        The other map's samples that count as surface (aligned).
    spacing : float
        The map's median spacing (metres): the lines' width and step follow it.

    Returns
    -------
    ndarray, shape (m,), bool
    """
    found = np.zeros(candidates.size, dtype=bool)
    if candidates.size == 0 or not solid.any():
        return found
    surface = np.ascontiguousarray(points[solid])
    own = KDTree(surface)
    both = KDTree(np.ascontiguousarray(np.vstack([surface, other_points])))
    width = NEAR_LINE * spacing
    along = np.arange(width, CLEAR_REACH, width)
    directions = _sphere(DIRECTIONS)
    for rank, index in enumerate(candidates):
        found[rank] = _sighted(points[index], own, both, along, directions)
    return found
