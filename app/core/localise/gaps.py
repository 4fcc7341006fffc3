"""Sampling gaps: the origin-free test of merged clouds (a candidate in a sampling gap of the
other's surface) and places between a ring lidar's lines (:func:`between_samples`).

Without any sensor origin, a candidate that lies *on* the other cloud's surface, inside a hole
of its sampling, is not a change: under each station of a merged survey lies a blind disc
(below the lidar's lowest ring) that the other stations cover only sparsely, at grazing
angles, or not at all, so a dense point of the other epoch there finds no neighbour within a
few local spacings.  The neighbourhood here adapts to the hole: in each of
:data:`SECTORS` directions around the candidate, in its own surface's plane, probes at
doubling distances (from its nearest-point distance up to :data:`MAX_GAP` metres) look for a
point of the other cloud on that plane (within the tolerance, with an agreeing normal) in
that direction.  The candidate is in a gap when every direction finds one: the other cloud's
surface surrounds it.  A shadow's rim, an added box's faces or a removed box's points fail
(the other cloud's points lie on one side only, or on other planes).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from app.core.localise.settings import GATHER_CHUNK
from app.core.localise.surface import LocalGeometry

__all__ = [
    "MAX_GAP",
    "PLANE_RADIUS_FACTOR",
    "SECTORS",
    "between_samples",
    "coplanar_near_probe",
    "in_sampling_gap",
    "on_sampled_planes",
    "tangent_directions",
]

SECTORS = 6
"""Directions (60 degrees apart) in which the other cloud's surface must be found."""
SECTOR_HALF_ANGLE_COSINE = math.cos(math.radians(45.0))
"""A point of the other cloud counts for a direction within 45 degrees of it."""
PROBE_DOUBLINGS = 6
"""Probes at 1, 2, 4, ... 32 nearest-point distances in each direction (capped at MAX_GAP)."""
MAX_GAP = 4.0
"""Largest distance (metres) from the candidate at which the surrounding surface counts: a
blind disc is at most about 3 m across (a sensor 1.5 m up, 45 degrees below horizontal)."""
PLANE_SLOPE = math.sin(math.radians(1.0))
"""The plane tolerance grows by this much a metre away from the candidate (surfaces bend)."""
NORMAL_AGREEMENT_COSINE = math.cos(math.radians(30.0))
PROBE_NEIGHBOURS = 4
SURROUNDING_SAMPLES = 64
""":func:`between_samples` looks at most at this many samples (nearest first)."""
MAX_SURROUNDING_GAP = math.radians(150.0)
"""Surrounded: no angle wider than this between the directions to the samples in the plane (a
place past a straight edge of the samples has one of 180 degrees or more; the margin is for
noisy samples along that edge)."""
PLANE_RADIUS_FACTOR = 2.0
"""Samples within this many change thresholds of a candidate give its planes
(:func:`on_sampled_planes`): lines up to twice that apart are bridged."""
PLANE_SAMPLES = 32
""":func:`on_sampled_planes` picks a candidate's nearest plane among this many samples."""
PLANE_CHUNK = GATHER_CHUNK * 12 // PLANE_SAMPLES
SURROUNDING_CHUNK = GATHER_CHUNK * 12 // SURROUNDING_SAMPLES
"""Places per step of :func:`between_samples`: (chunk, 64, 3) float64 gathers as large as a
:data:`~app.core.localise.settings.GATHER_CHUNK` gather of 12 neighbours."""


def tangent_directions(
    normal: NDArray[np.floating], sectors: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Unit normals and ``sectors`` evenly spread unit directions in each point's tangent plane.

    Parameters
    ----------
    normal : ndarray, shape (c, 3)
    sectors : int

    Returns
    -------
    unit : ndarray, shape (c, 3)
    directions : ndarray, shape (c, sectors, 3)
    """
    unit = normal.astype(np.float64)
    unit /= np.maximum(np.linalg.norm(unit, axis=1), 1e-12)[:, None]
    helper = np.where(np.abs(unit[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    first = np.cross(unit, helper)
    first /= np.linalg.norm(first, axis=1)[:, None]
    second = np.cross(unit, first)
    angles = 2.0 * math.pi * np.arange(sectors) / sectors
    directions = (
        np.cos(angles)[None, :, None] * first[:, None, :]
        + np.sin(angles)[None, :, None] * second[:, None, :]
    )
    return unit, directions


def coplanar_near_probe(
    query: NDArray[np.float64],
    unit: NDArray[np.float64],
    direction: NDArray[np.float64],
    reach: NDArray[np.float64],
    cloud: LocalGeometry,
    tolerance: float,
    *,
    max_distance: float,
    half_angle_cosine: float,
) -> NDArray[np.bool_]:
    """Whether ``cloud`` has a point on each query's plane near its probe, in its direction.

    Parameters
    ----------
    query, unit, direction : ndarray, shape (p, 3)
        Candidate, its unit normal, the probe's unit direction in its plane.
    reach : ndarray, shape (p,)
        The probe's distance from the candidate.
    cloud : LocalGeometry
    tolerance : float
        Largest offset (metres) from the candidate's plane, at the candidate.
    max_distance : float
        Points farther (metres) from the candidate do not count.
    half_angle_cosine : float
        A point counts for the direction within this cosine of it.

    Returns
    -------
    ndarray, shape (p,), bool
    """
    k = min(PROBE_NEIGHBOURS, cloud.points.shape[0])
    _, index = cloud.tree.query(query + reach[:, None] * direction, k=k)
    index = np.asarray(index).reshape(query.shape[0], k)
    offset = cloud.points[index] - query[:, None, :]  # (p, k, 3)
    distance = np.linalg.norm(offset, axis=2)
    across = np.abs(np.einsum("pkd,pd->pk", offset, unit))
    along = np.einsum("pkd,pd->pk", offset, direction)
    agrees = np.abs(np.einsum("pkd,pd->pk", cloud.normal[index], unit))
    hit = (
        (distance <= max_distance)
        & (across <= tolerance + PLANE_SLOPE * distance)
        & (along >= half_angle_cosine * distance)
        & (agrees >= NORMAL_AGREEMENT_COSINE)
    )
    return hit.any(axis=1)


def in_sampling_gap(
    points: NDArray[np.float64],
    normal: NDArray[np.floating],
    nearest_distance: NDArray[np.float64],
    *,
    other: LocalGeometry,
    tolerance: float,
) -> NDArray[np.bool_]:
    """Whether each point lies in a sampling gap of the other cloud's surface.

    Parameters
    ----------
    points : ndarray, shape (c, 3)
        Change candidates of one cloud.
    normal : ndarray, shape (c, 3)
        Unit normal of each candidate's own surface.
    nearest_distance : ndarray, shape (c,)
        Distance of each candidate to its nearest point in the other cloud.
    other : LocalGeometry
        The other cloud (its KD-tree, points and normals).
    tolerance : float
        Largest offset (metres) from the candidate's plane, at the candidate: ``tau``.

    Returns
    -------
    ndarray, shape (c,), bool
        In each of :data:`SECTORS` directions in the candidate's plane, within
        :data:`MAX_GAP`, the other cloud has a point on that plane whose normal agrees.
    """
    count = points.shape[0]
    result = np.zeros(count, dtype=bool)
    if count == 0:
        return result
    for start in range(0, count, GATHER_CHUNK):
        chunk = slice(start, start + GATHER_CHUNK)
        query = points[chunk]
        unit, directions = tangent_directions(normal[chunk], SECTORS)
        found = np.zeros((query.shape[0], SECTORS), dtype=bool)
        step = np.maximum(nearest_distance[chunk], 1e-3)
        for doubling in range(PROBE_DOUBLINGS):
            reach = np.minimum(step * 2.0**doubling, MAX_GAP)
            hit = coplanar_near_probe(
                np.repeat(query, SECTORS, axis=0),
                np.repeat(unit, SECTORS, axis=0),
                directions.reshape(-1, 3),
                np.repeat(reach, SECTORS),
                other,
                tolerance,
                max_distance=MAX_GAP,
                half_angle_cosine=SECTOR_HALF_ANGLE_COSINE,
            )
            found |= hit.reshape(query.shape[0], SECTORS)
        result[chunk] = found.all(axis=1)
    return result


def between_samples(
    points: NDArray[np.float64],
    normal: NDArray[np.floating],
    cloud: LocalGeometry,
    *,
    radius: float,
    tolerance: float,
) -> NDArray[np.bool_]:
    """Whether each place lies between ``cloud``'s samples of a plane through it.

    A ring lidar samples a floor or a box top in lines a few to tens of centimetres apart,
    wider than a sample's spacing along its line: a place between two lines is on that surface
    though no sample lies near it.  The samples within ``radius`` (at most
    :data:`SURROUNDING_SAMPLES`, with a fitted plane) whose plane passes within ``tolerance``
    of the place are that surface's; projected onto the place's plane they surround it when no
    angle between the directions to them exceeds :data:`MAX_SURROUNDING_GAP` (the place lies
    inside them, not past their edge).  Unlike :func:`in_sampling_gap` the reach is bounded:
    only gaps narrower than twice ``radius`` are bridged.

    Parameters
    ----------
    points : ndarray, shape (c, 3)
    normal : ndarray, shape (c, 3)
        Unit normal of the plane at each place.
    cloud : LocalGeometry
    radius, tolerance : float
        Metres.

    Returns
    -------
    ndarray, shape (c,), bool
    """
    count = points.shape[0]
    surrounded = np.zeros(count, dtype=bool)
    k = min(SURROUNDING_SAMPLES, cloud.points.shape[0])
    if count == 0 or k < 3:
        return surrounded
    for start in range(0, count, SURROUNDING_CHUNK):
        rows = slice(start, start + SURROUNDING_CHUNK)
        point = points[rows]
        found, index = cloud.tree.query(point, k=k, distance_upper_bound=radius)
        index = np.minimum(np.asarray(index).reshape(len(point), k), cloud.points.shape[0] - 1)
        offset = cloud.points[index] - point[:, None, :]  # (c, k, 3)
        plane_offset = np.einsum("ckd,ckd->ck", offset, cloud.normal[index].astype(np.float64))
        on_plane = (
            (np.asarray(found).reshape(len(point), k) <= radius)
            & (np.abs(plane_offset) <= tolerance)
            & ~cloud.linear[index]
        )
        surrounded[rows] = _largest_gap(offset, normal[rows], on_plane) <= MAX_SURROUNDING_GAP
    return surrounded


def _largest_gap(
    offset: NDArray[np.float64], normal: NDArray[np.floating], valid: NDArray[np.bool_]
) -> NDArray[np.float64]:
    """Widest angle (radians) between the in-plane directions to the valid offsets, shapes
    (c, k, 3), (c, 3), (c, k) -> (c,); 2 pi with fewer than three of them."""
    _, directions = tangent_directions(normal, 4)  # 0 and 90 degrees: the plane's axes
    angle = np.arctan2(
        np.einsum("ckd,cd->ck", offset, directions[:, 1]),
        np.einsum("ckd,cd->ck", offset, directions[:, 0]),
    )
    angle = np.sort(np.where(valid, angle, np.inf), axis=1)
    count = valid.sum(axis=1)
    finite = np.isfinite(angle)
    angle = np.where(finite, angle, 0.0)
    rows = np.arange(angle.shape[0])
    # the wrap-around gap from the last valid direction back to the first
    wrap = angle[:, 0] + 2.0 * math.pi - angle[rows, np.maximum(count - 1, 0)]
    steps = np.where(finite[:, 1:], np.diff(angle, axis=1), 0.0)
    largest = np.maximum(steps.max(axis=1), wrap)
    return np.where(count >= 3, largest, 2.0 * math.pi)


def on_sampled_planes(
    points: NDArray[np.float64],
    distance: NDArray[np.float64],
    candidate: NDArray[np.bool_],
    cloud: LocalGeometry,
    *,
    radius: float,
    tolerance: float,
    change_threshold: float,
    nearest_distance: NDArray[np.float64] | None = None,
) -> NDArray[np.bool_]:
    """Candidates within the change threshold of a plane ``cloud`` sampled all around them.

    A point's distance to the other cloud's surface counts only the support discs of that
    cloud's samples (:func:`~app.core.localise.distance.surface_distance`), each a few local
    spacings wide.  A ring lidar samples a floor in lines farther apart than that: a removed
    box's foot, 3-7 cm over the floor a later path saw in lines 20 cm apart, measures 10-14 cm
    to the nearest line, though it lies within the change threshold of the floor.  Of the
    ``cloud`` samples within ``radius`` of such a candidate, the plane it lies nearest to is
    the surface when its foot on that plane lies between that plane's samples
    (:func:`between_samples`): there its distance is its offset from that plane.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    distance : ndarray, shape (n,)
        Distance to ``cloud``'s surface; lowered in place where a sampled plane is nearer.
    candidate : ndarray, shape (n,), bool
    cloud : LocalGeometry
        The other cloud.
    radius, tolerance, change_threshold : float
        Metres: the reach of the samples, ``tau`` and ``c``.
    nearest_distance : ndarray, shape (n,), optional
        Each point's distance to ``cloud``'s nearest sample, if known: a candidate with no
        sample within ``radius`` has no sampled plane and is not looked at (the same result;
        most of an added object's points, ~1.2 CPU s of a 1M-point pair's 1.3 otherwise).

    Returns
    -------
    ndarray, shape (n,), bool
        ``candidate`` without the points within ``change_threshold`` of such a plane.
    """
    kept = candidate.copy()
    if cloud.points.shape[0] < 3:
        return kept
    reachable = candidate if nearest_distance is None else candidate & (nearest_distance <= radius)
    candidates = np.flatnonzero(reachable)
    for start in range(0, candidates.size, PLANE_CHUNK):
        rows = candidates[start : start + PLANE_CHUNK]
        on_plane, plane_distance = _nearest_sampled_plane(
            points[rows],
            cloud,
            radius=radius,
            tolerance=tolerance,
            reach=change_threshold,
        )
        distance[rows[on_plane]] = plane_distance[on_plane]
        kept[rows[on_plane]] = False
    return kept


def _nearest_sampled_plane(
    points: NDArray[np.float64],
    cloud: LocalGeometry,
    *,
    radius: float,
    tolerance: float,
    reach: float,
) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
    """Whether each point (shape (c, 3)) lies within ``reach`` of the plane of one of
    ``cloud``'s samples within ``radius`` (the one it lies nearest to) with its foot on that
    plane between the plane's samples, and its offset from that plane (shapes (c,), (c,))."""
    k = min(PLANE_SAMPLES, cloud.points.shape[0])
    found, index = cloud.tree.query(points, k=k, distance_upper_bound=radius)
    index = np.minimum(np.asarray(index).reshape(len(points), k), cloud.points.shape[0] - 1)
    normal = cloud.normal[index].astype(np.float64)  # (c, k, 3)
    offset = np.einsum("ckd,ckd->ck", points[:, None, :] - cloud.points[index], normal)
    valid = (np.asarray(found).reshape(len(points), k) <= radius) & ~cloud.linear[index]
    nearest = np.argmin(np.where(valid, np.abs(offset), np.inf), axis=1)
    rows = np.arange(len(points))
    # the samples whose normals agree with that sample's are the plane's: their mean normal
    # and their median offset along it (one sample's normal tilts by noise, and the least of
    # k noisy offsets lies low)
    agreeing = np.einsum("ckd,cd->ck", normal, normal[rows, nearest])
    on_it = valid & (np.abs(agreeing) >= NORMAL_AGREEMENT_COSINE)
    plane_normal = np.einsum("ck,ckd->cd", np.where(on_it, np.sign(agreeing), 0.0), normal)
    plane_normal /= np.maximum(np.linalg.norm(plane_normal, axis=1), 1e-12)[:, None]
    along = np.einsum("ckd,cd->ck", points[:, None, :] - cloud.points[index], plane_normal)
    ranked = np.sort(np.where(on_it, along, np.inf), axis=1)
    count = on_it.sum(axis=1)
    median = 0.5 * (
        ranked[rows, np.maximum(count - 1, 0) // 2] + ranked[rows, np.minimum(count // 2, k - 1)]
    )
    plane_distance = np.where(valid[rows, nearest], np.abs(median), np.inf)
    on_plane = plane_distance <= reach
    near = np.flatnonzero(on_plane)
    if near.size:
        foot = points[near] - median[near, None] * plane_normal[near]
        on_plane[near] = between_samples(
            foot, plane_normal[near], cloud, radius=radius, tolerance=tolerance
        )
    return on_plane, plane_distance
