"""Flying candidates on a line of sight past an own edge: flying where the other map holds them.

A depth camera's flying pixel lies on its pixel's line of sight between a near surface's edge and
the surface behind it: from the pixel towards the camera the line grazes the near surface's
edge and then runs through the open room to the camera; away from the camera it meets the
surface behind.  A fused map keeps no camera position, but the open room tells where a camera
could have been: a sample with :data:`SIGHT_LINES` directions along which (i) an own sample
lies close to the line a little in front (the edge), (ii) past that edge both maps leave the
line empty up to :data:`CLEAR_REACH` (a camera could see along it) and (iii) an own sample lies
on the line behind it, is where a flying pixel would be.

Only the flying candidates that :data:`~app.core.localise.flying_samples.OTHER_NEAR` keeps (a
sample of the other map within one median spacing) are tested: a turned chair's old surface
under the other map's flying pixels (drifting RGB-D rooms 503 / 303: 2 + 9 such pixels kept
45 / 308 of the chair's points unchanged) holds them as a thin part both maps saw would.  A
thin part seen past an edge with a wall behind it can look the same along a few lines (a real
sample just behind a silhouette); such samples have fewer lines of sight than a fan behind a
long edge, hence the count.
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
    "NEAR_LINE",
    "SIGHT_LINES",
    "on_sight_lines",
]

DIRECTIONS = 600
"""Directions tried per candidate (a Fibonacci sphere, ~8 degrees apart)."""
NEAR_LINE = 0.01
"""Metres: a sample this close to a point of a line lies on it (about half an RGB-D room's
median spacing), also the step along a line; the space past the edge is empty when no sample
of either map lies within 1.5 times this of the line."""
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
EDGE_START = 0.015
"""Metres in front of the candidate where the edge may start (its own neighbours are nearer)."""
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


def _sighted(
    candidate: NDArray[np.float64],
    own: KDTree,
    both: KDTree,
    along: NDArray[np.float64],
    directions: NDArray[np.float64],
) -> bool:
    """Whether one candidate (shape (3,)) has :data:`SIGHT_LINES` of ``directions`` (unit,
    shape (d, 3)) along which an own run of samples starts within :data:`EDGE_REACH` in front
    (the edge), both maps leave the line empty past it up to :data:`CLEAR_REACH`, and an own
    sample lies behind it; ``along``: the steps along each line, metres."""
    towards = candidate - directions[:, None, :] * along[None, :, None]
    hit = _near(own, towards, NEAR_LINE)
    blocked = _near(both, towards, 1.5 * NEAR_LINE)
    index = np.arange(along.size)
    front = hit & (along >= EDGE_START)
    begin = np.where(front.any(axis=1), front.argmax(axis=1), along.size)
    past = ~hit & (index > begin[:, None])
    after = np.where(past.any(axis=1), past.argmax(axis=1), along.size)
    clear = ~(blocked & (index >= after[:, None] + 2)).any(axis=1)
    last = along[np.clip(after - 1, 0, along.size - 1)]
    open_line = (begin < along.size) & (last <= EDGE_REACH) & (after + 2 < along.size) & clear
    if not open_line.any():
        return False
    behind = candidate + directions[open_line][:, None, :] * along[None, :, None]
    backed = (_near(own, behind, NEAR_LINE) & (along >= BEHIND_START)).any(axis=1)
    return int(backed.sum()) >= SIGHT_LINES


def on_sight_lines(
    points: NDArray[np.float64],
    candidates: NDArray[np.intp],
    solid: NDArray[np.bool_],
    other_points: NDArray[np.float64],
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
    along = np.arange(NEAR_LINE, CLEAR_REACH, NEAR_LINE)
    directions = _sphere(DIRECTIONS)
    for rank, index in enumerate(candidates):
        found[rank] = _sighted(points[index], own, both, along, directions)
    return found
