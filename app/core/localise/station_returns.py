"""Which returns a station of a merged cloud cannot have taken: those hidden by its own.

A station's returns are the rays of the ray test (:mod:`app.core.localise.station_rays`).  The
per-point station index of a merged cloud is often assigned from the stations' rings
(:func:`~app.core.localise.station_assignment.assign_stations`), and a few per cent of the
points go to the wrong station.  Such a point may lie behind a surface that station saw (the
far side of a solid rack): taken for one of that station's rays, it passes through the
surface in front of it, and every candidate on that surface is "seen through".

One sensor takes one return per direction, so a return lying, within about one angular step,
clearly behind the surface of a nearer return of the same station (the plane test of
:func:`~app.core.localise.rays.ray_visibility`'s occlusion) was not taken by that station, or
lies just past a silhouette edge.  Either way it is moved along its ray onto that surface
(:func:`on_hiding_surface`): what the station saw in that direction.  Dropping it instead
would unhide what lies behind it, for the station's other rays to pass through.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.localise.settings import CHUNK

__all__ = ["hidden_returns", "on_hiding_surface"]

AROUND_STEPS = 1.25
"""A return's neighbours by direction: the station's returns within this many of its angular
steps (its regular grid puts the nearest about one step apart)."""
AROUND_RETURNS = 8
"""Most neighbours looked at per return."""
MIN_HIDING = 1
"""A return is hidden when at least this many neighbours hide it (a true return just past a
silhouette edge is one too: it only loses that ray)."""
STEP_SAMPLE = 4096
"""Returns whose angular neighbours measure the station's typical angular step."""


def hidden_returns(
    points: NDArray[np.float64],
    origin: NDArray[np.float64],
    normal: NDArray[np.float32],
    linear: NDArray[np.bool_],
    *,
    tolerance: float,
) -> NDArray[np.bool_]:
    """The returns attributed to one station that a nearer return of it, in the same
    direction, hides.

    Parameters
    ----------
    points : ndarray, shape (m, 3)
        The returns attributed to the station.
    origin : ndarray, shape (3,)
        The station.
    normal : ndarray, shape (m, 3)
        Unit normal of each return's surface.
    linear : ndarray, shape (m,), bool
        Returns without a fitted plane: they hide whatever lies beyond them.
    tolerance : float
        Metres: how far behind a nearer return's plane (and farther along the ray) a return
        must lie to be hidden; at least half the angular step times the range is added.

    Returns
    -------
    ndarray, shape (m,), int64
        For a return with :data:`MIN_HIDING` neighbours by direction (:data:`AROUND_STEPS`)
        clearly nearer, with the return clearly behind each one's plane (or with no plane),
        the index of the nearest by direction of them; -1 for the others.
    """
    count = points.shape[0]
    hider = np.full(count, -1, dtype=np.int64)
    if count <= MIN_HIDING:
        return hider
    offset = np.asarray(points, dtype=np.float64) - origin
    ranges = np.linalg.norm(offset, axis=1)
    valid = ranges > 0
    direction = np.zeros((count, 3), dtype=np.float32)
    direction[valid] = offset[valid] / ranges[valid, None]
    tree = KDTree(direction)
    sample = np.linspace(0, count - 1, min(STEP_SAMPLE, count)).astype(np.int64)
    sample_step, _ = tree.query(direction[sample], k=3)
    step = float(np.median(sample_step[:, 2]))
    for start in range(0, count, CHUNK):
        rows = np.arange(start, min(start + CHUNK, count))
        angle, other = tree.query(
            direction[rows], k=AROUND_RETURNS + 1, distance_upper_bound=AROUND_STEPS * step
        )
        found = np.isfinite(angle) & (other != rows[:, None])
        other = np.minimum(other, count - 1)
        margin = (tolerance + 0.5 * step * ranges[rows])[:, None]
        # the near return's plane, with the station on its front side: behind it by > margin
        near_normal = normal[other].astype(np.float64)  # (c, k, 3)
        front = -np.sign(np.einsum("ckd,ckd->ck", offset[other], near_normal))
        behind = -front * np.einsum("ckd,ckd->ck", offset[rows, None] - offset[other], near_normal)
        farther = ranges[other] < ranges[rows, None] - margin
        hides = found & farther & (linear[other] | (behind > margin))
        # the nearest by direction of the returns that hide it (the query sorts by angle)
        first = np.argmax(hides, axis=1)
        chosen = hides.sum(axis=1) >= MIN_HIDING
        hider[rows[chosen]] = other[chosen, first[chosen]]
    return np.where(valid, hider, -1)


def on_hiding_surface(
    points: NDArray[np.float64],
    origin: NDArray[np.float64],
    normal: NDArray[np.float32],
    linear: NDArray[np.bool_],
    *,
    tolerance: float,
) -> tuple[NDArray[np.float64], NDArray[np.float32], NDArray[np.bool_]]:
    """One station's returns with each hidden one (:func:`hidden_returns`) moved along its
    ray onto the surface that hides it: what the station saw in that direction.

    Parameters and shapes as :func:`hidden_returns`; returns ``points``, ``normal`` and
    ``linear`` (copies where changed), the moved returns taking their hider's range, normal
    and linearity.  A moved return still stops the ray short of whatever lies behind it (it
    hides it, as the surface did) and never passes through that surface.
    """
    hider = hidden_returns(points, origin, normal, linear, tolerance=tolerance)
    moved = np.flatnonzero(hider >= 0)
    if moved.size == 0:
        return points, normal, linear
    points, normal, linear = points.copy(), normal.copy(), linear.copy()
    offset = points[moved] - origin
    hider_range = np.linalg.norm(points[hider[moved]] - origin, axis=1)
    points[moved] = origin + offset * (hider_range / np.linalg.norm(offset, axis=1))[:, None]
    normal[moved] = normal[hider[moved]]
    linear[moved] = linear[hider[moved]]
    return points, normal, linear
