"""Candidates judged by their surface, not one point's distance: the surfaces a little over the
change threshold from the other cloud's, and the surfaces crossing the other cloud's.

:func:`surface_offset_candidates` judges a point just under the change threshold by the median
levels of both clouds' points along its surface's axis (noisy samples of a surface a little
over the threshold straddle it); :func:`crossing_candidates` judges a point whose surface meets
the other cloud's at a steep angle by the noise-only threshold.  Both take
:func:`~app.core.localise.distance.surface_distance`'s distances and candidates.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from app.core.localise.distance import Side
from app.core.localise.settings import GATHER_CHUNK
from app.core.localise.surface import LocalGeometry, weighted_plane
from app.core.threads import for_each_chunk

__all__ = [
    "LEVEL_CHUNK",
    "LEVEL_NEIGHBOURS",
    "SPARSE_AXIS_SPACINGS",
    "crossing_candidates",
    "surface_offset_candidates",
]

LEVEL_NEIGHBOURS = 96
"""At most this many points within half the change threshold give a surface's axis and,
within :data:`LEVEL_RADIUS_FACTOR` local spacings of its normal line, its level
(:func:`surface_offset_candidates`)."""
LEVEL_RADIUS_FACTOR = 4.0
MIN_AXIS_POINTS = 12
"""Fewer points within half the change threshold give no axis of their own: the point takes
its fitted normal where its cloud is sampled sparsely for its noise
(:data:`SPARSE_AXIS_SPACINGS`), and keeps its own distance elsewhere."""
SPARSE_AXIS_SPACINGS = 3.0
"""A point whose local spacing is at least this many of its cloud's noise ``sigma`` has a
fitted normal (from its 10 neighbours, two spacings round) that noise hardly tilts: where half
the change threshold holds fewer than :data:`MIN_AXIS_POINTS` of its points, because the cloud
is sparse there (a robot map, 3-5 cm apart at 8 mm noise), that normal is its surface's axis.
A dense cloud's normals, at 1 cm spacing with 1.2 cm of depth noise, point anywhere."""
LEVEL_CHUNK = GATHER_CHUNK * 12 // LEVEL_NEIGHBOURS
"""Points judged per step of :func:`surface_offset_candidates`: its (chunk, 96, 3) float64
gathers are then as large as a :data:`~app.core.localise.settings.GATHER_CHUNK` gather of
k + 1 = 12 neighbours (0.56 MiB), under the 1 MiB mmap threshold (see the settings' note): a
2,048-point step's 4.7 MB temporaries faulted ~85k fresh pages in at 1M + 1M points."""


def surface_offset_candidates(
    candidate: NDArray[np.bool_],
    distance: NDArray[np.float64],
    own: Side,
    other: LocalGeometry,
    *,
    threshold: float,
    change_threshold: float,
    threads: int = 1,
) -> NDArray[np.bool_]:
    """Candidates, with the points just under the change threshold judged by their surface.

    A surface standing a little more than the change threshold from a surface of the other
    cloud (a backrest 10.9 cm in front of a wall, with 1.2 cm of depth noise) has its points'
    distances straddle the threshold, and each point's nearest point in the other cloud, the
    closest of many noisy samples, lies nearer still: about half of it, or none, becomes a
    candidate.  A point within ``min(tau, c - tau)`` under the change threshold ``c`` (none
    when noise sets the threshold) is judged by its surface: the axis of its points within
    ``c / 2`` (:data:`MIN_AXIS_POINTS` to :data:`LEVEL_NEIGHBOURS`; their fitted normals,
    from 10 neighbours, point anywhere at 1 cm noise), or its fitted normal where its cloud is
    sparse for its noise (:func:`_surface_axes`), and, along it, the median level of
    each cloud's points in a cylinder round its normal line (:func:`_level`).  It is a
    candidate when both clouds have points there and the two levels lie more than ``c``
    apart: a median of tens of samples, where the point had one.

    Parameters
    ----------
    candidate : ndarray, shape (n,), bool
    distance : ndarray, shape (n,)
        :func:`surface_distance`'s.
    own : Side
        The points' cloud (its neighbour index not yet released).
    other : LocalGeometry
    threshold, change_threshold : float
        ``tau`` and ``c`` (metres).
    threads : int
        Threads that judge the chunks of points (each writes its own rows: the same result on
        any number; the other cloud's points, judged on a thread of their own, may take much
        less time, and this cloud's chunks then still share both cores).

    Returns
    -------
    ndarray, shape (n,), bool
        ``candidate`` with the points found so added.
    """
    band = min(threshold, change_threshold - threshold)
    rows = np.flatnonzero(~candidate & (distance > change_threshold - band)) if band > 0 else []
    found = candidate.copy()
    geometry = own.geometry

    def judge(start: int) -> None:
        row = rows[start : start + LEVEL_CHUNK]
        point = geometry.points[row]
        unit, has_axis, ball = _surface_axes(geometry, row, change_threshold)
        toward = np.sign(np.einsum("cd,cd->c", other.points[own.nearest_index[row]] - point, unit))
        other_level, other_found = _level(
            point + (toward * distance[row])[:, None] * unit, point, unit, other, change_threshold
        )
        # the own level only where the other cloud has points on the line (each row's level is
        # its own: the same answers; at 1M + 1M ~0.3 % of the rows); its first ball is the
        # axis's (same centre and radius): not queried again
        wanted = np.flatnonzero(has_axis & other_found)
        own_level, own_found = _level(
            point[wanted],
            point[wanted],
            unit[wanted],
            geometry,
            change_threshold,
            first_ball=(ball[0][wanted], ball[1][wanted]),
        )
        found[row[wanted]] = own_found & (
            np.abs(other_level[wanted] - own_level) > change_threshold
        )

    for_each_chunk(judge, range(0, len(rows), LEVEL_CHUNK), threads)
    return found


CROSSING_COSINE = 0.5
"""A point's surface crosses the other cloud's surface when their normals meet at more than
60 degrees (|cos| under this): an upright face standing on a floor, a floor under a wall."""


def crossing_candidates(
    candidate: NDArray[np.bool_],
    distance: NDArray[np.float64],
    own: Side,
    other: LocalGeometry,
    crossing_threshold: float,
) -> NDArray[np.bool_]:
    """Candidates, with the points whose own surface crosses the other cloud's judged by the
    noise alone.

    The change threshold holds the alignment residual (the spread of the offsets between the
    surfaces both clouds have, which on a real map also takes up the ground's own level
    changes and drift: 6.3 cm on the MLS bike-parking pair, making the threshold 27.6 cm).
    A point whose own surface meets the other cloud's nearest surface at more than 60 degrees
    (:data:`CROSSING_COSINE`; a fence or a bicycle standing on the ground the other epoch saw
    bare) is no offset sample of that surface: its distance is its height over it, along its
    own surface.  It is a candidate when that distance, and its nearest point's, exceed
    ``crossing_threshold`` (the noise-only ``tau``, at least ``min_change_distance``): the low
    band of a removed or added object, which the full threshold left unchanged (the MLS
    fences' lowest 10-28 cm, 115 and 188 points).  None is added where the change threshold
    is the crossing one already.

    Parameters
    ----------
    candidate : ndarray, shape (n,), bool
    distance : ndarray, shape (n,)
        :func:`surface_distance`'s.
    own : Side
        The points' cloud.
    other : LocalGeometry
    crossing_threshold : float
        Metres.

    Returns
    -------
    ndarray, shape (n,), bool
        ``candidate`` with the points found so added.
    """
    rows = np.flatnonzero(
        ~candidate & (distance > crossing_threshold) & (own.nearest_distance > crossing_threshold)
    )
    found = candidate.copy()
    if rows.shape[0] == 0:
        return found
    own_normal = own.geometry.normal[rows].astype(np.float64)
    other_normal = other.normal[own.nearest_index[rows]].astype(np.float64)
    cosine = np.abs(np.einsum("cd,cd->c", own_normal, other_normal))
    found[rows[cosine < CROSSING_COSINE]] = True
    return found


def _surface_axes(
    geometry: LocalGeometry, row: NDArray[np.int64], change_threshold: float
) -> tuple[NDArray[np.float64], NDArray[np.bool_], tuple[NDArray, NDArray]]:
    """The axis of each ``row`` point's surface (shape (c, 3)), whether it has one (shape
    (c,)), and the ball it came from (the (distances, indices) of its
    :data:`LEVEL_NEIGHBOURS` nearest points within half the change threshold).

    The smallest eigenvector of the ball's points when it holds :data:`MIN_AXIS_POINTS`
    (the surface's axis from a wider neighbourhood than its fitted normal's: at 1 cm spacing
    with 1 cm of noise, 10 neighbours' normals point anywhere; within half the change
    threshold, as a sparse map's 96 nearest points reach round its corners).  With fewer, the
    point's fitted normal where its local spacing is :data:`SPARSE_AXIS_SPACINGS` noise
    ``sigma`` or more (the ball is short of points because the cloud is sparse there, and
    noise hardly tilts a fit two spacings round: a robot map's board 11 cm in front of a wall,
    3-5 cm between samples, had no axis and lost half its points to noise); none otherwise.
    """
    k = min(LEVEL_NEIGHBOURS, geometry.points.shape[0])
    reach = 0.5 * change_threshold
    point = geometry.points[row]
    found_distance, index = geometry.tree.query(point, k=k, distance_upper_bound=reach)
    near = np.asarray(found_distance).reshape(len(row), k) <= reach
    index = np.minimum(np.asarray(index).reshape(len(row), k), geometry.points.shape[0] - 1)
    _, _, vectors = weighted_plane(geometry.points[index], near.astype(np.float64))
    own_axis = near.sum(axis=1) >= MIN_AXIS_POINTS
    sparse = ~own_axis & (geometry.spacing[row] >= SPARSE_AXIS_SPACINGS * geometry.noise)
    unit = np.where(sparse[:, None], geometry.normal[row].astype(np.float64), vectors[:, :, 0])
    return unit, own_axis | sparse, (found_distance, index)


def _level(
    centre: NDArray[np.float64],
    point: NDArray[np.float64],
    unit: NDArray[np.float64],
    cloud: LocalGeometry,
    change_threshold: float,
    first_ball: tuple[NDArray, NDArray] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Median offset along ``unit`` from ``point`` of ``cloud``'s points in a cylinder around
    the normal line, gathered around ``centre``, and whether there were any (shapes (c, 3) ->
    (c,), (c,)).

    The :data:`LEVEL_NEIGHBOURS` nearest points of ``centre`` within half the change threshold,
    those within :data:`LEVEL_RADIUS_FACTOR` spacings of the line; re-centred once on their
    median, so that the ball, which truncates a noisy surface's spread, is centred on it.
    ``first_ball``: the (distances, indices) of ``cloud.tree``'s query around ``centre`` with
    that ``k`` and radius, when the caller has it already (the same result, one query fewer).
    A line with no point in its first ball keeps its level, so its second ball would be the
    first again: only the others are queried a second time."""
    k = min(LEVEL_NEIGHBOURS, cloud.points.shape[0])
    level = np.einsum("cd,cd->c", centre - point, unit)
    if first_ball is None:
        first_ball = cloud.tree.query(
            point + level[:, None] * unit, k=k, distance_upper_bound=0.5 * change_threshold
        )
    level, count = _ball_level(level, point, unit, cloud, change_threshold, first_ball)
    again = np.flatnonzero(count > 0)
    if again.size:
        probe = point[again] + level[again, None] * unit[again]
        ball = cloud.tree.query(probe, k=k, distance_upper_bound=0.5 * change_threshold)
        level[again], count[again] = _ball_level(
            level[again], point[again], unit[again], cloud, change_threshold, ball
        )
    return level, count > 0


def _ball_level(
    level: NDArray[np.float64],
    point: NDArray[np.float64],
    unit: NDArray[np.float64],
    cloud: LocalGeometry,
    change_threshold: float,
    ball: tuple[NDArray, NDArray],
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """One step of :func:`_level`: the median offset along ``unit`` (c, 3) from ``point``
    (c, 3) of the ball's (``cloud.tree``'s (distances, indices), (c, k)) points within the
    cylinder round the line, ``level`` (c,) where there are none; and their count (c,)."""
    k = min(LEVEL_NEIGHBOURS, cloud.points.shape[0])
    found, index = ball
    index = np.minimum(np.asarray(index).reshape(len(point), k), cloud.points.shape[0] - 1)
    offset = cloud.points[index] - point[:, None, :]
    along = np.einsum("ckd,cd->ck", offset, unit)
    lateral_squared = np.einsum("ckd,ckd->ck", offset, offset) - along**2
    radius = LEVEL_RADIUS_FACTOR * cloud.spacing[index[:, 0]]
    inside = (np.asarray(found).reshape(len(point), k) <= 0.5 * change_threshold) & (
        lateral_squared <= (radius**2)[:, None]
    )
    count = inside.sum(axis=1)
    ranked = np.sort(np.where(inside, along, np.inf), axis=1)
    rows = np.arange(len(point))
    median = 0.5 * (
        ranked[rows, np.maximum(count - 1, 0) // 2] + ranked[rows, np.minimum(count // 2, k - 1)]
    )
    return np.where(count > 0, median, level), count
