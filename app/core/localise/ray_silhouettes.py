"""Past a nearer object's silhouette: which rays short of a candidate do not hide it.

The ray test (:func:`~app.core.localise.rays.ray_visibility`) reads the (up to 8) returns
within 2.5 angular steps of a candidate's direction; any one of them ending on a surface the
candidate lies behind hides it.  A ring lidar's 8 rays span two or three rings: the ring below
a line of sight may end on a desk's or an old box's top while the rings nearest it pass over
the edge into the candidate's place (robot 2302's added chair behind a desk's edge, 2200's
moved box's new face over its old top).  Between a ray stopped short and a ray less than half
as far from the candidate's direction that reaches its place lies the nearer object's
silhouette edge, and the candidate, clearly nearer the reaching ray, is on its side: the
farther rays do not hide it, unless the candidate lies within the change threshold of such a
ray's line (the hider may run on unseen to within the threshold of it)
(``RayTest.silhouette_clearance``, meant for the trajectory test's pseudo-stations, whose
returns carry their own sensor positions).

Not enabled (s28): measured with the clearance ``c`` in the trajectory test, robot 2200 0.900 ->
0.991, 2302 0.929 -> 0.969, 300 0.909 -> 0.941 and no false point on the 39 unchanged scenes of
seeds 0-14 and 20-28, but on held-out seeds 30-32 a false region on unchanged 3101 (26 points of
a level top seen at grazing incidence from a sensor 0.2-0.4 m above it) and 3000 0.996 -> 0.904.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "SILHOUETTE_ANGLE_RATIO",
    "SILHOUETTE_TILT",
    "beside_silhouette",
    "past_silhouettes",
    "reaching_rays",
]

SILHOUETTE_ANGLE_RATIO = 2.0
"""A short ray is overruled only when more than this many times as far from the candidate's
direction as the nearest reaching ray (the edge between them, the candidate on the reaching
ray's side in two cases of three): from a fused RGB-D map's sparse rays (1.5 degree steps)
the nearest ray may pass beside an object the candidate stands behind, a hider only 1.5 times
as far off (RGB-D 104, unchanged: 51 false points with the nearest ray deciding)."""
SILHOUETTE_TILT = math.radians(5.0)
"""A reaching ray's end must lie off the candidate's plane by the tolerance and this angle
over its run along the plane (a normal a few degrees off, :func:`reaching_rays`)."""


def reaching_rays(
    candidate_rays: NDArray[np.bool_],
    readings: tuple[NDArray[np.float64], ...],
    *,
    tolerance: float,
) -> NDArray[np.bool_]:
    """The rays that reach a candidate's place and carry on into free space beyond it.

    Among ``candidate_rays`` (crossing the candidate's plane near it, hiding nothing), those
    ending clearly beyond the crossing (by the range margin) and beyond the candidate, and off
    its plane.  At a grazing incidence a ray ending on the candidate's own wall a few
    decimetres past its crossing passes the range margin although it never left the wall
    (robot 201: a wall seen at 82 degrees, rays ending 0.2 m past their crossings, 3 cm off
    the plane; TLS 2304's rack in s25): its end must lie off the plane by ``tolerance`` and
    :data:`SILHOUETTE_TILT` over its run along the plane.

    Parameters
    ----------
    candidate_rays : ndarray, shape (c, k), bool
    readings : tuple of ndarray
        ``(ray_range, crossing, point_range, margin, ray_dot_normal)``: each ray's range, its
        range where it crosses the candidate's plane, the candidate's range (shape (c,)), the
        range margin and the ray's direction dotted with the candidate's normal (the others
        shape (c, k)).
    tolerance : float
        How far (metres) a ray's end may lie off the candidate's plane and still be on it.

    Returns
    -------
    ndarray, shape (c, k), bool
    """
    ray_range, crossing, point_range, margin, ray_dot_normal = readings
    beyond = np.where(candidate_rays, ray_range - crossing, 0.0)
    incidence = np.abs(ray_dot_normal)
    run = beyond * np.sqrt(np.maximum(1.0 - incidence**2, 0.0))
    return (
        candidate_rays
        & (beyond > margin)
        & (ray_range > point_range[:, None])
        & (beyond * incidence > tolerance + math.tan(SILHOUETTE_TILT) * run)
    )


def beside_silhouette(reaching: NDArray[np.bool_], angle: NDArray[np.float64]) -> NDArray[np.bool_]:
    """The rays clearly farther from each candidate's direction than its nearest reaching ray:
    more than :data:`SILHOUETTE_ANGLE_RATIO` times its angle.

    Parameters
    ----------
    reaching : ndarray, shape (c, k), bool
        :func:`reaching_rays`.
    angle : ndarray, shape (c, k)
        Each ray's angle from the candidate's direction (radians; inf for no ray).

    Returns
    -------
    ndarray, shape (c, k), bool
        Those rays: a ray among them that ends short of the candidate does not hide it.
    """
    nearest = np.where(reaching, angle, np.inf).min(axis=1)
    return angle > SILHOUETTE_ANGLE_RATIO * nearest[:, None]


def past_silhouettes(
    hides: NDArray[np.bool_],
    crosses_near: NDArray[np.bool_],
    readings: tuple[NDArray[np.float64], ...],
    limits: tuple[float, float, float],
) -> NDArray[np.bool_]:
    """``hides`` without the rays beside a silhouette, shape (c, k).

    Parameters
    ----------
    hides : ndarray, shape (c, k), bool
        The ray ends short of the candidate, on a surface the candidate lies behind.
    crosses_near : ndarray, shape (c, k), bool
        The ray crosses the candidate's plane near it.
    readings : tuple of ndarray
        As for :func:`reaching_rays`, then each ray's angle from the candidate's direction
        (radians, inf for no ray; shape (c, k)).
    limits : (float, float, float)
        The normal and range tolerances (metres: a ray's end within their root sum of squares
        of the candidate's plane is on it) and the clearance (metres, ``c``): a short ray whose
        line passes within it of the candidate (its angle times the candidate's range), or
        that ends within it short of the candidate, still hides it.  Its object, whose edge
        lies anywhere between the two rays, may come within ``c`` of the candidate, which the
        truth then calls unchanged: a desk top at the sensors' height, sampled only at its
        front edge, runs on under a removed board's foot 2-6 cm over it (robot 402); a box's
        face 9 cm in front of an unchanged upright beside its edge (robot 504: 27 false points
        on the upright, 1 region, without the range term).

    Returns
    -------
    ndarray, shape (c, k), bool
        The rays that still hide the candidate: those no clearly nearer ray reaching it
        overrules (:func:`beside_silhouette` of :func:`reaching_rays`).
    """
    normal_tolerance, range_tolerance, clearance = limits
    tolerance = math.hypot(normal_tolerance, range_tolerance)
    reaching = reaching_rays(crosses_near & ~hides, readings[:5], tolerance=tolerance)
    ray_range, point_range, angle = readings[0], readings[2][:, None], readings[5]
    clear = (angle * point_range > clearance) & (point_range - ray_range > clearance)
    return hides & ~(beside_silhouette(reaching, angle) & clear)
