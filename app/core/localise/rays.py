"""The ray visibility test: what the other sensor saw in the direction of each change candidate.

The other cloud's returns are indexed by direction from its origin (a KD-tree on unit vectors:
a spherical range image that adapts to any ray pattern).  For each candidate, the returns
within a few angular steps of its direction are compared with where each ray meets the
candidate's own surface (its plane): a return clearly short of the candidate (or of that
crossing) means it was occluded, no return means out of range or field of view (both
*unobserved*); rays that cross the candidate's plane near it, where its own cloud has surface,
and carry on clearly beyond it saw free space there (*seen through*); rays that end there saw
the surface (*surface*); a candidate whose plane no ray meets near it was seen *edge-on*.
A return short of the candidate hides it only when the candidate lies behind that return's
surface (its fitted plane): near the floor or a wall seen at a grazing angle, the rays just
beside the candidate's direction end on that surface short of the candidate without hiding it.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.localise.gaps import between_samples
from app.core.localise.ray_silhouettes import SilhouetteReadings, past_silhouettes
from app.core.localise.settings import CHUNK, GATHER_CHUNK
from app.core.localise.surface import LocalGeometry
from app.core.threads import for_each_chunk

__all__ = ["Candidates", "RayTest", "ray_visibility"]

MIN_INCIDENCE_COSINE = math.cos(math.radians(85.0))
"""Rays meeting a candidate's plane at more than 85 degrees incidence graze it: no evidence."""
STATUS_SURFACE = 0
STATUS_SEEN_THROUGH = 1
STATUS_UNOBSERVED = -1
STATUS_EDGE_ON = 2
"""Visibility of a change candidate: the other sensor saw a surface where it is (unchanged),
saw free space through it (changed), could not see it (unobserved), or saw its surface only
edge-on (changed if most of its connected candidates were seen through, else unobserved)."""
OWN_SUPPORT_FACTOR = 0.75
"""A ray's crossing of a candidate's plane is evidence only within this many own spacings of
an own point (stricter than the support radius: only evidence is lost, never invented)."""
VISIBILITY_RAYS = 8
ANGULAR_SAMPLE = 4096
"""Returns whose angular neighbours measure the other sensor's typical angular step."""


@dataclass(frozen=True)
class Candidates:
    """One cloud's change candidates and what the visibility test needs of each.

    Attributes
    ----------
    index : ndarray, shape (c,), int64
        Indices into the cloud.
    points : ndarray, shape (c, 3), float64
    normal : ndarray, shape (c, 3), float32
        Normal of the candidate's flattest neighbour (its own is tilted near edges).
    linear : ndarray, shape (c,), bool
        The flattest neighbour's neighbourhood is a line: no normal, so no evidence.
    spacing : ndarray, shape (c,), float64
        The cloud's local spacing at each candidate.
    surface_distance : ndarray, shape (c,), float64
        Distance to the other cloud's surface.
    """

    index: NDArray[np.int64]
    points: NDArray[np.float64]
    normal: NDArray[np.float32]
    linear: NDArray[np.bool_]
    spacing: NDArray[np.float64]
    surface_distance: NDArray[np.float64]

    def rows(self, chunk: slice) -> Candidates:
        """The candidates of ``chunk``."""
        return Candidates(
            **{field.name: getattr(self, field.name)[chunk] for field in dataclasses.fields(self)}
        )


@dataclass(frozen=True)
class RayTest:
    """How the ray visibility test reads the other sensor's returns.

    Attributes
    ----------
    normal_tolerance : float
        How far (metres) a candidate may lie off its true surface: threshold_factor x its
        cloud's noise and the registration residual.
    range_tolerance : float
        threshold_factor x the other cloud's noise (the error of its ranges).
    margin_factor, angle_factor, beyond_fraction, miss_factor : float
        The ``visibility_*`` parameters (:data:`~app.core.localise.settings.DEFAULT_PARAMETERS`).
    gap_radius : float
        Metres: a ray's crossing of a candidate's plane with no own point near it is over the
        own surface when the own cloud's samples of that plane within this radius surround it
        (:func:`~app.core.localise.gaps.between_samples`: a surface sampled in lines spans the
        gaps between them), for the rays that pass clearly beyond the plane; 0: never.
    silhouette_clearance : float
        Metres; positive: a return short of a candidate does not hide it when a ray less than
        half as far from the candidate's direction reaches its place and carries on into free
        space beyond it, and the candidate lies farther than this off the short ray's line
        and beyond its end, and the short ray's return lies clearly apart from the candidate's
        surface (more than this in front of its plane, the candidate more than this behind
        the return's plane): the nearer object's silhouette edge lies between the two rays, the
        candidate on the reaching ray's side (:mod:`~app.core.localise.ray_silhouettes`).
        0: never.  Only for rays from
        sensor positions known per return (the trajectory test's pseudo-stations, with ``c``):
        a station's returns assigned by geometry may belong to another station, and its lone
        far rays then reach.
    """

    normal_tolerance: float
    range_tolerance: float
    margin_factor: float
    angle_factor: float
    beyond_fraction: float
    miss_factor: float
    gap_radius: float = 0.0
    silhouette_clearance: float = 0.0


@dataclass(frozen=True)
class _Rays:
    """The other sensor's returns indexed by direction (see :func:`ray_visibility`)."""

    origin: NDArray[np.float64]  # (3,)
    range: NDArray[np.float64]  # (m,) distance of each return from the origin
    direction: NDArray[np.float32]  # (m, 3) unit vector from the origin to each return
    tree: KDTree  # on ``direction``
    normal: NDArray[np.float32] | None  # (m, 3) each return's surface normal, or None
    linear: NDArray[np.bool_] | None  # (m,) no plane fitted at the return (its normal unused)


def ray_visibility(
    candidates: Candidates,
    *,
    own: LocalGeometry,
    other_points: NDArray[np.float64],
    other_origin: NDArray[np.float64],
    test: RayTest,
    other_normals: NDArray[np.float32] | None = None,
    other_linear: NDArray[np.bool_] | None = None,
    threads: int = 1,
) -> tuple[NDArray[np.int8], float]:
    """What the other sensor saw in the direction of each candidate.

    The other cloud's returns are indexed by direction from its origin.  For each candidate,
    the returns within ``test.angle_factor`` typical angular steps of its direction are
    compared with where each of those rays would meet the candidate's own surface (the plane
    through it with its normal): a ray that stops clearly before the candidate (or before
    meeting that plane) means something is in front of it, unless the candidate lies clearly
    in front of the plane of the surface that return hit (:func:`_hides`); a ray that meets
    the plane near the candidate (within ``max(miss_factor * spacing, surface_distance)``),
    where its own cloud has surface all along the stretch over which it may meet that surface
    (:func:`_over_own_surface`), and carries on clearly beyond it saw free space where the
    candidate's surface would be.

    Parameters
    ----------
    candidates : Candidates
        c candidates of the own cloud.
    own : LocalGeometry
        The candidates' own cloud: a ray's crossing of a candidate's plane counts only within
        :data:`OWN_SUPPORT_FACTOR` own spacings of an own point.
    other_points : ndarray, shape (m, 3)
        The other cloud, whose sensor was at ``other_origin``.
    other_origin : ndarray, shape (3,)
    test : RayTest
    other_normals : ndarray, shape (m, 3), optional
        Unit normal of the surface at each return.  Without them every return short of a
        candidate hides it.
    other_linear : ndarray, shape (m,), bool, optional
        Returns without a fitted plane (their normals are not used: they hide what lies
        beyond them).
    threads : int
        Chunks of candidates tested at once (:func:`~app.core.threads.for_each_chunk`; the
        same statuses).

    Returns
    -------
    status : ndarray, shape (c,), int8
        1 "seen through": at least ``beyond_fraction`` of the rays meeting the candidate's
        surface near it pass clearly beyond it, and none stops clearly before it; -1
        "unobserved": no return in that direction (out of range or field of view), one stops
        clearly before the candidate (occluded); 2 "edge-on": no ray meets the candidate's
        surface near it; 0 "surface": the rays end where the candidate's surface is.
    angular_step : float
        The other sensor's typical angular step (radians).
    """
    other_range, other_direction, kept = _ranges_and_directions(other_points, other_origin)
    if other_normals is None:
        other_linear = None
    elif other_linear is None:
        other_linear = np.zeros(other_normals.shape[0], dtype=bool)
    if other_normals is not None and other_linear is not None and kept is not None:
        other_normals, other_linear = other_normals[kept], other_linear[kept]
    direction_tree = KDTree(other_direction)
    sample = np.linspace(0, other_range.shape[0] - 1, min(ANGULAR_SAMPLE, other_range.shape[0]))
    sample_step, _ = direction_tree.query(
        np.ascontiguousarray(other_direction[sample.astype(np.int64)]), k=3
    )
    angular_step = float(np.median(sample_step[:, 2]))
    rays = _Rays(
        other_origin, other_range, other_direction, direction_tree, other_normals, other_linear
    )
    status = np.empty(candidates.points.shape[0], dtype=np.int8)

    def test_rays(chunk: slice) -> None:
        status[chunk] = _ray_status(
            candidates.rows(chunk),
            own=own,
            rays=rays,
            test=test,
            max_angle=test.angle_factor * angular_step,
            angular_step=angular_step,
        )

    count = candidates.points.shape[0]
    chunks = (slice(start, start + GATHER_CHUNK) for start in range(0, count, GATHER_CHUNK))
    for_each_chunk(test_rays, chunks, threads)
    return status, angular_step


def _ranges_and_directions(
    points: NDArray[np.float64], origin: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float32], NDArray[np.bool_] | None]:
    """Range and unit direction of each return from the sensor (returns at the origin dropped).

    Computed in chunks into float32 directions (angular resolution ~1e-7 rad, far below any
    lidar's step), so the direction index costs 12 bytes a return and no (m, 3) temporary.

    Parameters
    ----------
    points : ndarray, shape (m, 3)
    origin : ndarray, shape (3,)

    Returns
    -------
    range : ndarray, shape (r,), float64
    direction : ndarray, shape (r, 3), float32
    kept : ndarray, shape (m,), bool, or None
        Which returns were kept (None: all of them).
    """
    count = points.shape[0]
    ranges = np.empty(count)
    directions = np.empty((count, 3), dtype=np.float32)
    for start in range(0, count, CHUNK):
        chunk = slice(start, start + CHUNK)
        offset = points[chunk] - origin
        ranges[chunk] = np.sqrt(np.einsum("md,md->m", offset, offset))
        with np.errstate(divide="ignore", invalid="ignore"):
            directions[chunk] = offset / ranges[chunk, None]
    valid = ranges > 0
    if not valid.all():
        return ranges[valid], directions[valid], valid
    return ranges, directions, None


def _ray_status(
    candidates: Candidates,
    *,
    own: LocalGeometry,
    rays: _Rays,
    test: RayTest,
    max_angle: float,
    angular_step: float,
) -> NDArray[np.int8]:
    """Visibility status of a chunk of candidates (the body of :func:`ray_visibility`).

    Parameters
    ----------
    candidates : Candidates
        A chunk of c candidates.
    own : LocalGeometry
    rays : _Rays
    test : RayTest
    max_angle : float
        Returns within this angle (radians, as a chord of unit vectors) of a candidate's
        direction are the other sensor's view of it.
    angular_step : float
        The other sensor's typical angular step (radians).

    Returns
    -------
    ndarray, shape (c,), int8
    """
    points, normals, linear = candidates.points, candidates.normal, candidates.linear
    spacing, surface_distance = candidates.spacing, candidates.surface_distance
    normal_tolerance, range_tolerance = test.normal_tolerance, test.range_tolerance
    margin_factor, miss_factor = test.margin_factor, test.miss_factor
    other_origin, other_range, other_direction = rays.origin, rays.range, rays.direction
    offset = points - other_origin
    point_range = np.linalg.norm(offset, axis=1)
    angle, ray = rays.tree.query(
        (offset / np.maximum(point_range, 1e-12)[:, None]).astype(np.float32),
        k=min(VISIBILITY_RAYS, other_range.shape[0]),
        distance_upper_bound=max_angle,
    )
    found = np.isfinite(angle)
    ray = np.minimum(ray, other_range.shape[0] - 1)
    ray_range = other_range[ray]
    ray_direction = other_direction[ray].astype(np.float64)  # (p, k, 3)
    normals = normals.astype(np.float64)
    # where each ray meets the plane through the point: origin + crossing * direction; rays
    # that graze the plane (or points without a normal) cannot say whether the surface is there
    ray_dot_normal = np.einsum("pkd,pd->pk", ray_direction, normals)
    grazing = (np.abs(ray_dot_normal) < MIN_INCIDENCE_COSINE) | linear[:, None]
    offset_dot_normal = np.einsum("pd,pd->p", offset, normals)
    with np.errstate(divide="ignore", invalid="ignore"):
        crossing = offset_dot_normal[:, None] / ray_dot_normal
    crosses_ahead = found & ~grazing & np.isfinite(crossing) & (crossing > 0)
    crossing = np.where(crosses_ahead, crossing, np.inf)
    crossing_point = (
        other_origin + np.where(crosses_ahead, crossing, 0.0)[..., None] * ray_direction
    )
    miss_distance = np.linalg.norm(crossing_point - points[:, None, :], axis=2)
    miss_tolerance = np.maximum(miss_factor * spacing, surface_distance)
    crosses_near = crosses_ahead & (miss_distance <= miss_tolerance[:, None])
    # a point off its surface by e lies e / cos(incidence) along the ray from the surface
    cos_incidence = np.where(grazing, 1.0, np.abs(ray_dot_normal))
    margin = margin_factor * np.sqrt((normal_tolerance / cos_incidence) ** 2 + range_tolerance**2)
    # A return short of the point hides it only when the point lies behind that return's
    # surface (without the other cloud's normals: every short return hides it).
    hides = found & (ray_range < point_range[:, None] - margin)
    if rays.normal is not None and rays.linear is not None:
        short_rows, short_rays = np.nonzero(hides)
        short_returns = ray[short_rows, short_rays]
        hides[short_rows, short_rays] = rays.linear[short_returns] | _hides(
            points[short_rows],
            rays.origin,
            ray_range[short_rows, short_rays],
            ray_direction[short_rows, short_rays],
            rays.normal[short_returns],
            tolerance=np.maximum(
                margin_factor * math.hypot(normal_tolerance, range_tolerance),
                0.5 * angular_step * point_range[short_rows],
            ),
        )
    if test.silhouette_clearance > 0.0:  # a clearly nearer ray reaching it: see past
        readings = (ray_range, crossing, point_range, margin, ray_dot_normal, angle)
        hides = _past_silhouettes(hides, crosses_near, readings, (candidates, rays, ray), test)
    # A ray that hides the point and stops clearly before its crossing too occludes the point
    # whatever the test below decides (the expected stop is one of the two): such points are
    # unobserved already, and most candidates of a moved sensor are (its shadows).
    occluded_anyway = ~found.any(axis=1) | (hides & (ray_range < crossing - margin)).any(axis=1)
    # ... and only where the own cloud has surface (a table top's, not past its edge)
    near = np.nonzero(crosses_near & ~occluded_anyway[:, None])
    readings = _Readings(
        hides,
        ray_range > crossing + margin,
        ray_range,
        crossing,
        point_range,
        margin,
        found.any(axis=1),
    )
    crossing_rays = (
        crossing_point[near],
        ray_direction[near],
        normals[near[0]],
        ray_dot_normal[near],
    )
    return _status_over_own_surface(own, crosses_near, near, crossing_rays, readings, test)


def _past_silhouettes(
    hides: NDArray[np.bool_],
    crosses_near: NDArray[np.bool_],
    readings: tuple[NDArray[np.float64], ...],
    chunk: tuple[Candidates, _Rays, NDArray[np.int64]],
    test: RayTest,
) -> NDArray[np.bool_]:
    """``hides`` (shape (c, k)) without the rays beside a nearer object's silhouette
    (:func:`~app.core.localise.ray_silhouettes.past_silhouettes`; ``readings``: the first six
    fields of :class:`~app.core.localise.ray_silhouettes.SilhouetteReadings`; ``chunk``: the
    candidates, the other sensor's returns and the returns read, shape (c, k))."""
    candidates, rays, ray = chunk
    return_normal = None  # NaN where no plane was fitted
    if rays.normal is not None and rays.linear is not None:
        return_normal = np.where(
            rays.linear[ray][..., None], np.nan, rays.normal[ray].astype(np.float64)
        )
    silhouette_readings = SilhouetteReadings(
        *readings,
        points=candidates.points,
        normals=candidates.normal.astype(np.float64),
        origin=rays.origin,
        ray_direction=rays.direction[ray].astype(np.float64),
        return_normal=return_normal,
    )
    limits = (test.normal_tolerance, test.range_tolerance, test.silhouette_clearance)
    return past_silhouettes(hides, crosses_near, silhouette_readings, limits)


class _Readings(NamedTuple):
    """What a chunk's rays say (:func:`_ray_status`), shapes (c, k) unless said.

    ``hides``: the ray stops short of the candidate, behind the surface it hit; ``passes``: it
    carries on clearly beyond its crossing of the candidate's plane; ``ray_range``,
    ``crossing`` (its range there), ``point_range`` (c,) the candidate's, ``margin`` the
    range margin; ``found_any`` (c,): the candidate has rays at all.
    """

    hides: NDArray[np.bool_]
    passes: NDArray[np.bool_]
    ray_range: NDArray[np.float64]
    crossing: NDArray[np.float64]
    point_range: NDArray[np.float64]
    margin: NDArray[np.float64]
    found_any: NDArray[np.bool_]


def _status_over_own_surface(
    own: LocalGeometry,
    crosses_near: NDArray[np.bool_],
    near: tuple[NDArray[np.int64], NDArray[np.int64]],
    crossing_rays: tuple[NDArray[np.float64], ...],
    readings: _Readings,
    test: RayTest,
) -> NDArray[np.int8]:
    """Each candidate's status (shape (c,)), its ``near`` rays (row and ray indices into the
    (c, k) ``crosses_near``, updated in place) counted only where they cross the own surface
    (:func:`_over_own_surface`; ``crossing_rays``: its first four arguments for those rays).

    With ``test.gap_radius``, a ray passing clearly beyond a crossing between the own cloud's
    sampling lines crosses the surface too, but only for the candidates not seen through
    without it: such a ray only adds a ray through the surface, so a candidate seen through
    without it stays so (the same statuses, for fewer rays' probes).
    """
    own_surface = functools.partial(
        _over_own_surface,
        own,
        reach=test.margin_factor * test.normal_tolerance,
        normal_tolerance=test.normal_tolerance,
    )
    crosses_near[near] = own_surface(*crossing_rays)
    status = _combined_status(crosses_near, readings, test.beyond_fraction)
    if test.gap_radius <= 0.0:
        return status
    rows, rays = near
    bridged = np.flatnonzero(
        ~crosses_near[near] & readings.passes[near] & (status[rows] != STATUS_SEEN_THROUGH)
    )
    if bridged.size == 0:
        return status
    crosses_near[rows[bridged], rays[bridged]] = own_surface(
        *(part[bridged] for part in crossing_rays), gap_radius=test.gap_radius
    )
    return _combined_status(crosses_near, readings, test.beyond_fraction)


def _combined_status(
    crosses_near: NDArray[np.bool_], readings: _Readings, beyond_fraction: float
) -> NDArray[np.int8]:
    """Each candidate's status (shape (c,)) from its rays: ``crosses_near`` (c, k), the ray
    meets the candidate's own surface near it."""
    point_range = readings.point_range[:, None]
    expected_stop = np.where(crosses_near, np.minimum(readings.crossing, point_range), point_range)
    stops_before = readings.hides & (readings.ray_range < expected_stop - readings.margin)
    passes_beyond = crosses_near & readings.passes
    n_near = crosses_near.sum(axis=1)
    occluded = ~readings.found_any | stops_before.any(axis=1)
    seen_through = passes_beyond.sum(axis=1) >= beyond_fraction * np.maximum(n_near, 1)
    status = np.where(seen_through, STATUS_SEEN_THROUGH, STATUS_SURFACE)
    status = np.where(n_near == 0, STATUS_EDGE_ON, status)
    return np.where(occluded, STATUS_UNOBSERVED, status).astype(np.int8)


def _over_own_surface(
    own: LocalGeometry,
    crossing_point: NDArray[np.float64],
    ray_direction: NDArray[np.float64],
    normal: NDArray[np.float64],
    ray_dot_normal: NDArray[np.float64],
    *,
    reach: float,
    normal_tolerance: float,
    gap_radius: float | NDArray[np.float64] = 0.0,
) -> NDArray[np.bool_]:
    """Whether a ray meets the candidate's own surface wherever it may meet it, not beside it.

    The surface is known to within ``reach`` of its plane, so a ray meets it somewhere within
    ``reach / cos(incidence)`` of its plane crossing along the ray: on the plane, within
    ``reach * tan(incidence)`` of the crossing along the ray's in-plane direction.  The ray
    went through the surface only if the own cloud has surface (a point within
    :data:`OWN_SUPPORT_FACTOR` spacings) at the crossing and at both ends of that stretch.  At
    a grazing incidence the stretch is long: a ray passing just beside a silhouette edge
    crosses the plane just beyond the edge's last points and is no evidence that the surface
    is gone (it can only be where the surface is when the edge is farther than the stretch).

    Parameters
    ----------
    own : LocalGeometry
        The candidates' own cloud.
    crossing_point : ndarray, shape (s, 3)
        Where each ray meets its candidate's plane.
    ray_direction : ndarray, shape (s, 3)
        Unit direction of each ray.
    normal : ndarray, shape (s, 3)
        Unit normal of each ray's candidate.
    ray_dot_normal : ndarray, shape (s,)
        ``ray_direction . normal`` (not grazing: at least :data:`MIN_INCIDENCE_COSINE` in
        absolute value).
    reach : float
        How far (metres) the surface may lie off its plane.
    normal_tolerance : float
        The smallest own support radius (metres).
    gap_radius : float or ndarray, shape (s,)
        For a ray with a positive one, a place with no own point near it is over the own
        surface when the own samples of the candidate's plane within it surround it
        (:func:`~app.core.localise.gaps.between_samples`); the caller gives it only to the
        rays that pass clearly beyond the plane (free space where the surface would be; a ray
        ending on the plane between the lines may end on another surface meeting it there).

    Returns
    -------
    ndarray, shape (s,), bool
    """
    if crossing_point.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    # the ray's in-plane component has length sin(incidence); over reach / cos(incidence)
    # along the ray it moves reach * tan(incidence) along the plane
    in_plane = ray_direction - ray_dot_normal[:, None] * normal
    stretch = (reach / np.abs(ray_dot_normal))[:, None] * in_plane
    supported = np.ones(crossing_point.shape[0], dtype=bool)
    gap = np.broadcast_to(np.asarray(gap_radius, dtype=np.float64), supported.shape)
    for shift in (0.0, -1.0, 1.0):
        # only the rays still supported are asked (the others stay unsupported)
        rows = np.flatnonzero(supported)
        if rows.size == 0:
            break
        along = crossing_point[rows] + shift * stretch[rows] if shift else crossing_point[rows]
        own_distance, own_nearest = own.tree.query(along, k=1)
        own_support = np.maximum(OWN_SUPPORT_FACTOR * own.spacing[own_nearest], normal_tolerance)
        near = own_distance <= own_support
        # between the own cloud's sampling lines (a ring lidar's on a floor or a box top)
        bridged = np.flatnonzero(~near & (gap[rows] > 0.0))
        if bridged.size:
            radius = float(np.max(gap_radius))
            near[bridged] = between_samples(
                along[bridged], normal[rows[bridged]], own, radius=radius, tolerance=reach
            )
        supported[rows] = near
    return supported


def _hides(
    points: NDArray[np.float64],
    origin: NDArray[np.float64],
    ray_range: NDArray[np.float64],
    ray_direction: NDArray[np.float64],
    ray_normal: NDArray[np.float32],
    *,
    tolerance: NDArray[np.float64],
) -> NDArray[np.bool_]:
    """Whether a return short of a point hides it: the point is not clearly in front of its surface.

    A return's surface (the plane through it with its fitted normal) separates the sensor's
    side from the solid behind it; a point lying on the sensor's side of that plane, by more
    than ``tolerance``, sees the sensor along a segment that never enters the solid (for a
    convex one), so that return does not hide it.  This is what happens next to a floor or
    a wall seen at a grazing angle: the ray just below a box's foot ends on the floor short
    of the box.

    Parameters
    ----------
    points : ndarray, shape (s, 3)
        One point per short return.
    origin : ndarray, shape (3,)
        The sensor.
    ray_range : ndarray, shape (s,)
    ray_direction : ndarray, shape (s, 3)
        Range and unit direction of each return.
    ray_normal : ndarray, shape (s, 3)
        Normal of the surface at each return.
    tolerance : ndarray, shape (s,)
        How far (metres) in front of the plane each point must lie: the errors of the point
        and of the plane, and at least half the sensor's angular step times the point's
        range (nearer than that to a surface, the sensor cannot tell the point from it).

    Returns
    -------
    ndarray, shape (s,), bool
    """
    normal = ray_normal.astype(np.float64)
    return_point = origin + ray_range[:, None] * ray_direction
    point_offset = np.einsum("sd,sd->s", points - return_point, normal)
    # the sensor's offset from the plane is -range * (direction . normal): its sign is the
    # sensor's side (zero for a ray along the plane: such a return hides the point)
    sensor_side = -np.sign(np.einsum("sd,sd->s", ray_direction, normal))
    return ~(point_offset * sensor_side > tolerance)
