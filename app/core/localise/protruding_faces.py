"""Small changed faces standing just out past the other epoch's parallel face: an object turned
or moved so that its faces moved a little over the change threshold.

A box turned a quarter in place (0.545 x 0.33 m before, 0.33 x 0.545 m after, about the same
centre) has its old end faces 0.11 m outside the new box's long faces, just over the change
threshold: each end face is a change, yet in a sparse robot map it is a cluster of 20-25
changed points, under ``min_region_points``, and is dropped as noise.  Nothing of the other
epoch meets it at an angle (:mod:`~app.core.localise.turned_faces`): it faces the other box's
side, parallel.

:func:`protruding_faces` keeps such a small cluster as a region when it is an upright face
and most of its points stand, within two change thresholds, in front of a parallel face of the
other epoch's surface this epoch lacks (the other cloud's points farther than the change
threshold from this cloud's surface), on the side away from the body that face bounds: the
object's face stood out there in one epoch, where the other epoch's object was not.  The body
is taken from the other cloud's own points around that face (off its plane, between its foot
and its top: its meeting faces, its top and its far face).  A surface revealed
where an object was removed or moved away (a wall behind it) lies on the body's side of the
object's face, and is no protruding face; a level patch (a floor under it) is no upright face.
Only for the clouds the map, trajectory or station ray test judged
(:data:`~app.core.localise.turned_faces.SMALL_FACE_TESTS`; TLS 000's rotated box: its new end
face, 10 points under a floor of 30): the origin-free tests keep their noise floor.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.localise.isolated_clusters import isolated_clusters
from app.core.localise.map_faces import EDGE_FACTOR
from app.core.localise.map_parts import UPRIGHT_NORMAL_Z
from app.core.localise.regions import ChangedRegion, Clustering, mark_moved_surfaces
from app.core.localise.turned_faces import (
    ChangedPoints,
    SmallClusters,
    face_normal,
    small_clusters,
    small_face_sides,
    turned_faces,
)

__all__ = ["protruding_faces", "with_small_faces"]

PARALLEL_COSINE = 0.9
"""The other face's normals within about 25 degrees of the face's: parallel."""
FACING_SHARE = 0.5
"""This share of the face's points must stand before the other epoch's parallel face."""
FACING_NEIGHBOURS = 8
"""Each face point looks at this many nearest lacking points of the other cloud."""
MIN_FACING = 3
"""And at least this many."""
MIN_OFFSET_SHARE = 0.5
"""The faces stand this many change thresholds apart at least (median): not one surface."""
BODY_RADIUS = 0.5
"""Metres: the other cloud's points this near the other face may bound its body."""
BODY_NEIGHBOURS = 128
"""Of each of its points' this many nearest."""
MIN_BODY_POINTS = 3
"""Fewer of them say nothing of where the body lies."""


def _other_face(
    face: NDArray[np.float64],
    normal: NDArray[np.float64],
    lacking: tuple[NDArray[np.int64], KDTree],
    other: ChangedPoints,
    reach: float,
) -> NDArray[np.int64] | None:
    """The other cloud's lacking points (indices, and a tree over their positions) standing
    parallel before ``face`` (shape (p, 3), unit ``normal`` shape (3,)) within ``reach``, or
    None when too few of the face's points stand before them."""
    lacking, tree = lacking
    k = min(FACING_NEIGHBOURS, lacking.size)
    distance, index = tree.query(face, k=k, distance_upper_bound=reach)
    distance = np.asarray(distance).reshape(face.shape[0], -1)
    index = np.asarray(index, dtype=np.int64).reshape(face.shape[0], -1)
    near = distance <= reach
    safe = np.where(near, index, 0)
    met = other.side.geometry.normal[lacking[safe]].astype(np.float64)
    parallel = near & (np.abs(met @ normal) >= PARALLEL_COSINE)
    facing = parallel.any(axis=1)
    if np.count_nonzero(facing) < max(MIN_FACING, FACING_SHARE * face.shape[0]):
        return None
    return np.unique(lacking[safe[parallel]])


def _around(other: ChangedPoints, places: NDArray[np.float64]) -> NDArray[np.int64]:
    """The other cloud's points (indices) within :data:`BODY_RADIUS` of any of ``places``
    (shape (q, 3)), up to :data:`BODY_NEIGHBOURS` a place."""
    k = min(BODY_NEIGHBOURS, other.side.points.shape[0])
    distance, index = other.side.geometry.tree.query(places, k=k, distance_upper_bound=BODY_RADIUS)
    index = np.asarray(index, dtype=np.int64).ravel()
    return np.unique(index[np.isfinite(np.asarray(distance).ravel())])


def _outside_body(
    face: NDArray[np.float64],
    normal: NDArray[np.float64],
    other_face: NDArray[np.int64],
    other: ChangedPoints,
    change_threshold: float,
) -> bool:
    """Whether ``face`` (shape (p, 3), unit ``normal``) stands at least
    :data:`MIN_OFFSET_SHARE` change thresholds from the other cloud's ``other_face`` (indices)
    on the side away from the body that face bounds: the median side of the other cloud's
    points around it, off its plane, above its foot and not over its top (its meeting faces,
    its top and its far face)."""
    face_points = other.side.points[other_face]
    offset = float(np.median(face_points @ normal) - np.median(face @ normal))
    if abs(offset) < MIN_OFFSET_SHARE * change_threshold:
        return False
    around = _around(other, face_points)
    points = other.side.points[around]
    depth = (points - face_points.mean(axis=0)) @ normal
    low, high = face_points[:, 2].min(), face_points[:, 2].max()
    bounding = (
        (np.abs(depth) > change_threshold / 2)
        & (points[:, 2] > low + change_threshold)
        & (points[:, 2] < high + change_threshold)
    )
    if np.count_nonzero(bounding) < MIN_BODY_POINTS:
        return False
    return float(np.median(depth[bounding])) * offset > 0


def _small_upright_faces(
    own: ChangedPoints,
    floor: int,
    min_region_points: int,
    cluster_factor: float,
    known: SmallClusters | None = None,
) -> list[tuple[ChangedRegion, NDArray[np.float64], NDArray[np.float64]]]:
    """``own``'s clusters of ``floor`` to ``min_region_points`` changed points whose plane
    fit is upright: each as a region, its points (shape (p, 3)) and unit normal (shape (3,))."""
    small = small_clusters(own, floor, cluster_factor, known)
    faces = []
    for region in small:
        if region.n_points >= min_region_points:
            continue
        face = own.side.points[region.point_indices]
        normal = face_normal(face)
        if abs(normal[2]) < UPRIGHT_NORMAL_Z:
            faces.append((region, face, normal))
    return faces


def protruding_faces(
    changed: tuple[ChangedPoints, ChangedPoints],
    *,
    cluster_factor: float,
    min_region_points: int,
    change_threshold: float,
    known: SmallClusters | None = None,
) -> list[ChangedRegion]:
    """The clusters of changed points under ``min_region_points`` that stand out past the other
    epoch's parallel face, away from its body (module docstring), as regions.

    Parameters
    ----------
    changed : (ChangedPoints, ChangedPoints)
        The reference's and the scan's changed points (all of them, with the test that judged
        each cloud).
    cluster_factor : float
        Points closer than this many local spacings are one cluster.
    min_region_points : int
    change_threshold : float
        ``c`` (metres): the other cloud's points farther than it from this cloud's surface
        are surface this cloud lacks; a face stands before it within :data:`EDGE_FACTOR` of it.
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
        faces = _small_upright_faces(own, floor, min_region_points, cluster_factor, known)
        lacking = np.flatnonzero(other.distance > change_threshold)
        if not faces or lacking.size == 0:
            continue
        lacking_tree = KDTree(other.side.points[lacking])
        for region, face, normal in faces:
            other_face = _other_face(
                face, normal, (lacking, lacking_tree), other, EDGE_FACTOR * change_threshold
            )
            if other_face is not None and _outside_body(
                face, normal, other_face, other, change_threshold
            ):
                kept.append(region)
    return kept


def with_small_faces(
    regions: list[ChangedRegion],
    changed: tuple[ChangedPoints, ChangedPoints],
    *,
    cluster_factor: float,
    min_region_points: int,
    change_threshold: float,
    clusterings: dict[tuple[str, float], Clustering] | None = None,
) -> tuple[list[ChangedRegion], int]:
    """``regions`` with the small clusters kept as faces turned in place
    (:func:`~app.core.localise.turned_faces.turned_faces`), standing out past the other
    epoch's face (:func:`protruding_faces`) or far from everything the other epoch sampled
    (:func:`~app.core.localise.isolated_clusters.isolated_clusters`) added, largest first,
    removed and added ones side by side marked again
    (:func:`~app.core.localise.regions.mark_moved_surfaces`), and how many small clusters were
    kept.  ``clusterings``: the clouds' clusters of their changed points found already (by
    region kind and cluster factor, :attr:`SmallClusters.clusterings`), not found again."""
    settings = {
        "cluster_factor": cluster_factor,
        "min_region_points": min_region_points,
        "change_threshold": change_threshold,
    }
    # each cloud's small clusters, found once for the three rules
    known = SmallClusters(clusterings=dict(clusterings or {}))
    found = turned_faces(changed, regions, **settings, known=known)
    for more in (
        protruding_faces(changed, **settings, known=known),
        isolated_clusters(changed, **settings, known=known),
    ):
        seen = {(region.kind, int(region.point_indices[0])) for region in found}
        found += [
            region for region in more if (region.kind, int(region.point_indices[0])) not in seen
        ]
    if not found:
        return regions, 0
    merged = [*regions, *found]
    merged.sort(key=lambda region: (-region.n_points, region.kind, int(region.point_indices[0])))
    return mark_moved_surfaces(merged), len(found)
