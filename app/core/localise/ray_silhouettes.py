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
ray's line or of its end (the hider may run on unseen to within the threshold of it), or
that ray's return is not clearly apart from the candidate's surface (:func:`apart_from_returns`:
it may be the candidate's own object or surface) (``RayTest.silhouette_clearance``, set to
``c`` by the trajectory test's pseudo-stations, whose returns carry their own sensor positions).

Enabled in s29 with :func:`apart_from_returns`: built in s28, it had made a false region on
held-out unchanged robot 3101 (a box's side face past its own front face) and cost 3000 0.092
(a wall near a corner past its own nearer part).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "SILHOUETTE_ANGLE_RATIO",
    "SILHOUETTE_TILT",
    "SilhouetteReadings",
    "apart_from_returns",
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


class SilhouetteReadings(NamedTuple):
    """What :func:`past_silhouettes` reads of a chunk's c candidates and their k rays.

    ``ray_range``, ``crossing`` (each ray's range where it crosses the candidate's plane),
    ``margin`` (the range margin), ``ray_dot_normal`` (the ray's direction dotted with the
    candidate's normal) and ``angle`` (from the candidate's direction, radians, inf for no
    ray): shape (c, k); ``point_range`` (c,): the candidate's range; ``points`` (c, 3) and
    ``normals`` (c, 3): the candidates and their normals; ``origin`` (3,): the sensor;
    ``ray_direction`` (c, k, 3): unit directions; ``return_normal`` (c, k, 3): the normal of
    the surface each ray ended on (NaN where no plane was fitted), or None (no normals).
    """

    ray_range: NDArray[np.float64]
    crossing: NDArray[np.float64]
    point_range: NDArray[np.float64]
    margin: NDArray[np.float64]
    ray_dot_normal: NDArray[np.float64]
    angle: NDArray[np.float64]
    points: NDArray[np.float64]
    normals: NDArray[np.float64]
    origin: NDArray[np.float64]
    ray_direction: NDArray[np.float64]
    return_normal: NDArray[np.float64] | None


def apart_from_returns(readings: SilhouetteReadings, clearance: float) -> NDArray[np.bool_]:
    """Whether each ray's return lies on a surface clearly apart from its candidate's: more than
    ``clearance`` in front of the candidate's plane (on the sensor's side) while the candidate
    lies more than ``clearance`` behind the return's plane, shape (c, k).

    Only such a return can be a separate, nearer object whose silhouette edge a clearly nearer
    ray passes.  A candidate on a face of a convex object lies on a plane every other face of
    that object lies behind: a return behind the candidate's plane (or within ``clearance`` of
    it) may be the candidate's own object, and the ray reaching the candidate then passes that
    object's own far edge (held-out robot 3101: a box's side face seen at 75 degrees, the short
    rays ending on the box's front face 6 cm behind the side face's plane, the nearest ray
    passing 5 cm beyond the box's far edge onto a lower box's top: 22 false points, a region).
    A candidate within ``clearance`` of the return's plane may be on that surface, seen nearer
    along it (held-out robot 3000: a wall seen at 64 degrees 0.3 m from a corner, its candidates
    2 cm off the plane of the returns 0.5-2.4 m nearer on the same wall, their fitted normals
    tilted 10 degrees by the corner, the nearest rays ending on the end wall: 46 false points).
    A return without a fitted plane (NaN normal) is not apart.

    Parameters
    ----------
    readings : SilhouetteReadings
    clearance : float
        Metres (``c``).

    Returns
    -------
    ndarray, shape (c, k), bool
    """
    ray_range, ray_direction = readings.ray_range, readings.ray_direction
    offset_dot_normal = np.einsum("cd,cd->c", readings.points - readings.origin, readings.normals)
    # the return's height over the candidate's plane, on the sensor's side
    in_front = (
        np.abs(offset_dot_normal)[:, None]
        - np.sign(offset_dot_normal)[:, None] * ray_range * readings.ray_dot_normal
    )
    if readings.return_normal is None:
        return in_front > clearance
    return_normal = readings.return_normal
    ends = readings.origin + ray_range[..., None] * ray_direction
    # the candidate's depth behind the return's plane (the sensor's side is in front)
    sensor_side = -np.sign(np.einsum("ckd,ckd->ck", ray_direction, return_normal))
    behind = -sensor_side * np.einsum(
        "ckd,ckd->ck", readings.points[:, None, :] - ends, return_normal
    )
    with np.errstate(invalid="ignore"):
        return (in_front > clearance) & (behind > clearance)


def past_silhouettes(
    hides: NDArray[np.bool_],
    crosses_near: NDArray[np.bool_],
    readings: SilhouetteReadings,
    limits: tuple[float, float, float],
) -> NDArray[np.bool_]:
    """``hides`` without the rays beside a silhouette, shape (c, k).

    Parameters
    ----------
    hides : ndarray, shape (c, k), bool
        The ray ends short of the candidate, on a surface the candidate lies behind.
    crosses_near : ndarray, shape (c, k), bool
        The ray crosses the candidate's plane near it.
    readings : SilhouetteReadings
    limits : (float, float, float)
        The normal and range tolerances (metres: a ray's end within their root sum of squares
        of the candidate's plane is on it) and the clearance (metres, ``c``): a short ray whose
        line passes within it of the candidate (its angle times the candidate's range), that
        ends within it short of the candidate, or whose return is not clearly apart from the
        candidate's surface (:func:`apart_from_returns`) still hides it.  Its object, whose
        edge lies anywhere between the two rays, may come within ``c`` of the candidate, which
        the truth then calls unchanged: a desk top at the sensors' height, sampled only at its
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
    ray_range, point_range, angle = (
        readings.ray_range,
        readings.point_range[:, None],
        readings.angle,
    )
    clear = (angle * point_range > clearance) & (point_range - ray_range > clearance)
    overruled = beside_silhouette(reaching, angle) & clear
    if (hides & overruled).any():
        overruled &= apart_from_returns(readings, clearance)
    return hides & ~overruled
