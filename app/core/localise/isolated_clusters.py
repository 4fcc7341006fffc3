"""Small changed clusters far from everything the other epoch sampled: an object moved away.

Clusters of changed points smaller than ``min_region_points`` are dropped as noise (features
at the resolution limit, coverage edges).  A box a robot map saw from afar can be as small:
robot warehouse 1204's box (0.56 x 0.32 x 0.33 m) moved 18 m, seen in each epoch as 26 and
12 points, under a floor of 30.  Yet noise lies on or near surfaces both epochs sampled: an
offset sample, an edge, a strip one path reached, a sparse far return whose neighbours in the
other epoch are one sampling gap away.  The moved box's points stand 0.4 m and more from
every point of the other epoch, more than 1.5 times both clouds' sampling steps there.

:func:`isolated_clusters` keeps a small cluster (of :func:`~app.core.localise.turned_faces.
face_floor` points at least) as a region when its points' median distance to the nearest
point of the other cloud is at least :data:`ISOLATION_FACTOR` change thresholds and at least
:data:`GAP_FACTOR` times the larger of the two clouds' local spacings there (no sampling gap
of either cloud: a warehouse ceiling swept sparsely 9-10 m up has its nearest other points
one spacing away), and it spans a surface, not a line (its second principal extent at least
:data:`SPAN_FACTOR` of its own spacings: a single ring arc at the resolution limit is none),
and the other epoch saw its place empty over a support: the other cloud's highest points in
the column under it are level (the floor or top the object stood or stands on) and none lie
at its heights.  A patch only one epoch's path reached (a fused RGB-D room's corner the other
camera never looked at) has nothing of the other epoch under it, or the side of a wall.
Only for the clouds the map, trajectory or station ray test judged (:func:`~app.core.localise.
turned_faces.small_face_clouds`): the origin-free tests keep their noise floor.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from app.core.localise.map_sides import LEVEL_NORMAL_Z
from app.core.localise.regions import ChangedRegion
from app.core.localise.turned_faces import (
    ChangedPoints,
    SmallClusters,
    small_clusters,
    small_face_sides,
)

__all__ = ["isolated_clusters"]

ISOLATION_FACTOR = 4.0
"""A cluster's points stand this many change thresholds from the other cloud (median)."""
GAP_FACTOR = 1.5
"""And this many times the larger of both clouds' local spacings there: no sampling gap."""
SPAN_FACTOR = 1.0
"""Its second principal extent spans this many of its own spacings at least: no line of
single samples (a ring arc at the resolution limit is narrower than one spacing)."""
COLUMN_FACTOR = 2.0
"""The column over the cluster's footprint is widened by this many change thresholds."""
MIN_SUPPORT_POINTS = 3
"""The other cloud's level points under the cluster, fewer say nothing of its place."""


def _second_extent(points: NDArray[np.float64]) -> float:
    """The extent of ``points`` (shape (p, 3)) along their second principal axis (metres)."""
    centred = points - points.mean(axis=0)
    _, vectors = np.linalg.eigh(np.cov(centred.T))
    along = centred @ vectors[:, 1]
    return float(along.max() - along.min())


def _seen_empty_over_support(
    other: ChangedPoints, points: NDArray[np.float64], change_threshold: float
) -> bool:
    """Whether ``other`` saw the place of the cluster ``points`` (shape (p, 3)) empty: in the
    column over its footprint (widened by ``change_threshold``), its highest points under the
    cluster's foot are :data:`MIN_SUPPORT_POINTS` level ones (a floor or a top the object stood
    or stands on), and none lie at the cluster's own heights."""
    low, high = points.min(axis=0), points.max(axis=0)
    other_points = other.side.points
    margin = COLUMN_FACTOR * change_threshold
    column = np.flatnonzero(
        np.all(other_points[:, :2] >= low[:2] - margin, axis=1)
        & np.all(other_points[:, :2] <= high[:2] + margin, axis=1)
    )
    heights = other_points[column, 2]
    if np.any((heights >= low[2]) & (heights <= high[2])):
        return False
    below = column[heights < low[2]]
    if below.size < MIN_SUPPORT_POINTS:
        return False
    highest = below[np.argsort(other_points[below, 2])[-MIN_SUPPORT_POINTS:]]
    return bool(np.all(np.abs(other.side.geometry.normal[highest, 2]) >= LEVEL_NORMAL_Z))


def _isolated(
    own: ChangedPoints, other: ChangedPoints, members: NDArray[np.int64], change_threshold: float
) -> bool:
    """Whether ``own``'s cluster ``members`` (indices, shape (p,)) stands far from everything
    ``other`` sampled and spans a surface (module docstring)."""
    gap = float(np.median(own.side.nearest_distance[members]))
    if gap < ISOLATION_FACTOR * change_threshold:
        return False
    nearest = own.side.nearest_index[members].astype(np.int64)
    own_spacing = float(np.median(own.side.geometry.spacing[members]))
    other_spacing = float(np.median(other.side.geometry.spacing[nearest]))
    if gap < GAP_FACTOR * max(own_spacing, other_spacing):
        return False
    points = own.side.points[members]
    if _second_extent(points) < SPAN_FACTOR * own_spacing:
        return False
    return _seen_empty_over_support(other, points, change_threshold)


def isolated_clusters(
    changed: tuple[ChangedPoints, ChangedPoints],
    *,
    cluster_factor: float,
    min_region_points: int,
    change_threshold: float,
    known: SmallClusters | None = None,
) -> list[ChangedRegion]:
    """The clusters of changed points under ``min_region_points`` that stand far from every
    point of the other epoch (module docstring), as regions.

    Parameters
    ----------
    changed : (ChangedPoints, ChangedPoints)
        The reference's and the scan's changed points, with the test that judged each cloud.
    cluster_factor : float
        Points closer than this many local spacings are one cluster.
    min_region_points : int
    change_threshold : float
        ``c`` (metres): a cluster stands :data:`ISOLATION_FACTOR` of it from the other cloud.
    known : SmallClusters, optional
        The small clusters found so far (:func:`~app.core.localise.turned_faces.small_clusters`).

    Returns
    -------
    list of ChangedRegion
        The small clusters kept, reference's first.
    """
    floor, sides = small_face_sides(changed, min_region_points)
    kept: list[ChangedRegion] = []
    for own, other in sides:
        kept += [
            region
            for region in small_clusters(own, floor, cluster_factor, known)
            if region.n_points < min_region_points
            and _isolated(own, other, region.point_indices, change_threshold)
        ]
    return kept
