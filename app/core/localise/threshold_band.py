"""Changes carried on below a lifted change threshold: the band between 10 cm and ``c``.

A point is a change candidate when its distance to the other epoch's surface exceeds
``c = max(tau, min_change_distance)``.  Where the noise and the measured alignment residual
lift ``tau`` above ``min_change_distance`` (a real mobile-laser-scanning map: 4 cm of noise on
rough ground and vegetation and a 6 cm residual give ``c`` = 27.6 cm on the MultiChange3D
bike-parking pair), every point of a removed fence or an added bicycle that lies 10-27 cm from
the other epoch's ground is no candidate: the fence's foot rows and the bicycles' wheels
beside the shelter's posts (261 of that pair's 3,274 changed points, 8 %).  By the issue's
truth they are changed (more than 10 cm from every surface of the other epoch).

``tau`` guards against noise and misalignment, so a point in that band is not changed on its
own distance.  :func:`carried_changes` takes it as changed when it continues a change: it lies
within :data:`BAND_SPACINGS` of its local spacing of a changed point of a cluster of at least
``min_region_points`` (no new region grows from a dropped noise cluster), in at most
:data:`BAND_HOPS` steps, and its surface crosses the other epoch's surface there (their
normals more than :data:`CROSSING_DEGREES` apart: a fence standing on the ground, not a patch
of ground 12 cm off the other epoch's ground by noise, which would carry a change along the
whole floor).  It does nothing where ``c`` is ``min_change_distance`` (a dense, well aligned
map: every synthetic class of the bench), nor against a cloud with sensor origins.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.labels import LABEL_CHANGED, LABEL_UNCHANGED
from app.core.localise.distance import Side
from app.core.localise.regions import cluster_labels
from app.core.localise.visibility import Labelled

__all__ = ["BAND_HOPS", "BAND_SPACINGS", "CROSSING_DEGREES", "carried_changes", "carry_changes"]

BAND_HOPS = 2
"""Steps a change is carried into the band: a fence's foot is one or two rows of a map."""
BAND_SPACINGS = 2.0
"""A band point within this many of its local spacings of a changed point continues it."""
CROSSING_DEGREES = 45.0
"""A band point whose normal meets its nearest other point's at more than this crosses the
other epoch's surface (stands on it or hangs from it)."""


def carried_changes(
    points: NDArray[np.float64],
    label: NDArray[np.int8],
    distance: NDArray[np.float64],
    *,
    normal: NDArray[np.float32],
    other_normal: NDArray[np.float32],
    spacing: NDArray[np.float64],
    cluster_radius: NDArray[np.float64],
    limits: tuple[float, float],
    min_region_points: int,
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The band points (module docstring) that carry a change on, and the changed point each
    continues.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    label : ndarray, shape (n,), int8
        The visibility test's labels.
    distance : ndarray, shape (n,)
        Distance to the other epoch's surface.
    normal : ndarray, shape (n, 3)
        Each point's fitted normal.
    other_normal : ndarray, shape (n, 3)
        The fitted normal of each point's nearest point in the other epoch.
    spacing, cluster_radius : ndarray, shape (n,)
        The cloud's local spacing and the regions' cluster radius at each point.
    limits : (float, float)
        ``min_change_distance`` and the change threshold ``c`` (metres).
    min_region_points : int
        Smaller clusters of changed points carry nothing on.

    Returns
    -------
    carried : ndarray, shape (b,), int64
        Indices of the points now changed.
    source : ndarray, shape (b,), int64
        Index of the changed point each continues, through the band points between
        (its evidence and confidence are taken).
    """
    floor, change_threshold = limits
    none = np.zeros(0, dtype=np.int64)
    if change_threshold <= floor:
        return none, none
    crossing = np.abs(np.einsum("nd,nd->n", normal, other_normal)) < math.cos(
        math.radians(CROSSING_DEGREES)
    )
    band = np.flatnonzero(
        (label == LABEL_UNCHANGED) & (distance > floor) & (distance <= change_threshold) & crossing
    )
    changed = np.flatnonzero(label == LABEL_CHANGED)
    if band.shape[0] == 0 or changed.shape[0] == 0:
        return none, none
    clusters = cluster_labels(points[changed], cluster_radius[changed])
    seeds = changed[np.bincount(clusters)[clusters] >= min_region_points]
    origin = seeds
    carried, source = [], []
    for _ in range(BAND_HOPS):
        if seeds.shape[0] == 0 or band.shape[0] == 0:
            break
        reach, nearest = KDTree(points[seeds]).query(points[band], k=1)
        near = reach <= BAND_SPACINGS * spacing[band]
        carried.append(band[near])
        source.append(origin[nearest[near]])
        seeds, origin, band = band[near], origin[nearest[near]], band[~near]
    if not carried:
        return none, none
    return np.concatenate(carried), np.concatenate(source)


def carry_changes(
    own: Side,
    other: Side,
    labelled: Labelled,
    distance: NDArray[np.float64],
    *,
    limits: tuple[float, float],
    cluster_factor: float,
    min_region_points: int,
) -> None:
    """Label ``own``'s band points that carry a change on (:func:`carried_changes`) changed,
    in place, with the evidence and confidence of the change they continue, and report how
    many (``<own>_band_carried_points``); only against a map without sensor positions (the
    map test's clouds, as :func:`~app.core.localise.surface_levels.crossing_candidates`).  With
    the other epoch's origins, known or recovered (KITTI frames, Velodyne street scans:
    ``c`` 0.14-0.51 m from their alignment residual), the ray tests judge what they see and
    a band there is as likely the misalignment as a change.

    Parameters
    ----------
    own, other : Side
        The labelled cloud and the other one.
    labelled : Labelled
        ``own``'s labels after the visibility test (changed in place).
    distance : ndarray, shape (n,)
        ``own``'s distances to the other epoch's surface.
    limits : (float, float)
        ``min_change_distance`` and the change threshold ``c`` (metres).
    cluster_factor : float
        The regions' cluster radius in local spacings.
    min_region_points : int
        Smaller clusters of changed points carry nothing on.
    """
    if other.origins is not None:  # the ray tests judge a sensor's candidates: maps only
        labelled.report[f"{own.name}_band_carried_points"] = 0
        return
    spacing = own.geometry.spacing
    carried, source = carried_changes(
        own.points,
        labelled.label,
        distance,
        normal=own.geometry.normal,
        other_normal=other.geometry.normal[own.nearest_index],
        spacing=spacing,
        cluster_radius=cluster_factor * spacing,
        limits=limits,
        min_region_points=min_region_points,
    )
    labelled.label[carried] = LABEL_CHANGED
    labelled.evidence[carried] = labelled.evidence[source]
    labelled.confidence[carried] = labelled.confidence[source]
    labelled.report[f"{own.name}_band_carried_points"] = int(carried.shape[0])
