"""Small changed faces that meet a change of the other epoch at an angle: a face turned in place.

Clusters of changed points smaller than ``min_region_points`` are noise: features at the
resolution limit (an edge or a strip seen at a grazing angle) whose point count grows like the
square root of the cloud's.  A turned object's new face can be as small, in a sparse robot map
that saw it from afar (a chair turned a quarter in place: its new backrest 16 points at 140k
points a cloud, under a floor of about 30), and yet it is no noise: it meets the old face, a
change of the other epoch, at the corner they share, at an angle.

:func:`turned_faces` keeps such a small cluster as a region when it is an upright face whose
points meet an upright region of the other epoch at an edge (the two faces' normals at more
than 60 degrees, within two change thresholds): the object before and after it turned.  Where
no point of it lies that near, the two faces' planes may still meet in a vertical corner line
within that reach of both (a path that saw each face only from a little off the corner they
share: robot corridor 2800, the old backrest seen up to 0.17 m off it, the new one's changed
points ending short of it, where both backrests lie within the change threshold).  A
surface revealed where a removed object stood is none: it is level (the floor or a top under
it) or parallel to the removed object's face that hid it (the wall behind it).  For the
clouds the map test, the trajectory test or the station ray test judged
(:data:`SMALL_FACE_TESTS`): a terrestrial survey's far station samples an object's face as
sparsely (TLS 000, a box turned a quarter in place: its new end face 10 points at 140k points
a cloud, under a noise floor of 30).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.labels import LABEL_CHANGED
from app.core.localise.distance import Side
from app.core.localise.map_evidence import MapTest
from app.core.localise.map_faces import EDGE_COSINE, EDGE_FACTOR
from app.core.localise.map_parts import UPRIGHT_NORMAL_Z
from app.core.localise.regions import ChangedRegion, Clustering, find_regions
from app.core.localise.station_rays import StationRayTest
from app.core.localise.surface import principal_axes
from app.core.localise.trajectory_visibility import TrajectoryTest
from app.core.localise.visibility import Labelled

__all__ = [
    "CORNER_TESTS",
    "SMALL_FACE_TESTS",
    "ChangedPoints",
    "SmallClusters",
    "changed_points",
    "face_floor",
    "face_normal",
    "small_clusters",
    "small_face_clouds",
    "small_face_sides",
    "turned_faces",
]

SMALL_FACE_TESTS = (MapTest.name, TrajectoryTest.name, StationRayTest.name)
"""The visibility tests whose clouds' small faces are looked for: maps from a moving sensor
and surveys from stations, sparse where a sensor saw a face from afar (the noise floor
``min_region_points`` is meant for features at the resolution limit, not an object's face).
The origin-free surface and coverage tests keep their noise floor."""
FLOOR_SHARE = 1.0 / 3.0
"""A turned face has at least this share of ``min_region_points`` points (and 4)."""
MIN_MEETING = 3
"""Fewer of its points meeting the other epoch's region than this say nothing."""
MEETING_SHARE = 0.5
"""This share of its meeting points must meet the region's upright surface at an angle."""
CORNER_NEIGHBOURS = 16
"""The other region's points looked at per point of a face for the corner their planes meet in."""
CORNER_TESTS = (MapTest.name, TrajectoryTest.name)
"""The visibility tests whose clouds' small faces may meet a region at a corner line only
(:func:`_corner_points`): maps from a moving sensor, whose paths saw each face of a turned
object from places of their own.  Not the station ray test: on single street frames (the
Lidar-SCU pairs of ``bench.label_digests``, ``c`` 0.51 m) its reach is a metre and 6-point
faces of unknown truth met corner lines there."""


class ChangedPoints(NamedTuple):
    """One cloud's changed points, as the regions are drawn from them.

    Attributes
    ----------
    side : Side
    changed : ndarray, shape (n,), bool
    distance : ndarray, shape (n,)
        Each point's distance to the other cloud's surface.
    evidence : ndarray, shape (n,), int8
    confidence : ndarray, shape (n,)
    test : str
        The name of the visibility test that judged the cloud (``""`` when none did).
    """

    side: Side
    changed: NDArray[np.bool_]
    distance: NDArray[np.float64]
    evidence: NDArray[np.int8]
    confidence: NDArray[np.floating]
    test: str = ""


def changed_points(side: Side, labelled: Labelled, distance: NDArray[np.float64]) -> ChangedPoints:
    """``side``'s changed points (``labelled``; ``distance`` shape (n,)) and the name of the
    visibility test that judged them."""
    return ChangedPoints(
        side,
        labelled.label == LABEL_CHANGED,
        distance,
        labelled.evidence,
        labelled.confidence,
        str(labelled.report.get(f"{side.name}_visibility", "")),
    )


def face_floor(min_region_points: int) -> int:
    """The fewest points a small face kept as a region holds: :data:`FLOOR_SHARE` of
    ``min_region_points``, and 4 (none is kept when that is ``min_region_points`` or more)."""
    return max(4, int(np.ceil(FLOOR_SHARE * min_region_points)))


def small_face_clouds(
    changed: tuple[ChangedPoints, ChangedPoints],
) -> list[tuple[ChangedPoints, ChangedPoints]]:
    """``(own, other)`` for each cloud with changed points that one of
    :data:`SMALL_FACE_TESTS` judged, reference first: the clouds small faces are looked for
    in."""
    pairs = ((changed[0], changed[1]), (changed[1], changed[0]))
    return [
        (own, other) for own, other in pairs if own.test in SMALL_FACE_TESTS and own.changed.any()
    ]


def small_face_sides(
    changed: tuple[ChangedPoints, ChangedPoints], min_region_points: int
) -> tuple[int, list[tuple[ChangedPoints, ChangedPoints]]]:
    """The small-face floor (:func:`face_floor`) and the clouds small faces are looked for in
    (:func:`small_face_clouds`; none when the floor reaches ``min_region_points``)."""
    floor = face_floor(min_region_points)
    if floor >= min_region_points:
        return floor, []
    return floor, small_face_clouds(changed)


@dataclass
class SmallClusters:
    """What a comparison's small-cluster rules (:func:`turned_faces`, ``protruding_faces``,
    ``isolated_clusters``) hand on instead of clustering the same changed points again.

    Attributes
    ----------
    clusterings : dict
        Each cloud's clusters of its changed points
        (:class:`~app.core.localise.regions.Clustering`), by the cloud's region kind and the
        cluster factor: the regions step's (``min_region_points`` only filters them), reused
        for the smaller floor.
    regions : dict
        The small clusters found so far (:func:`small_clusters`), by region kind, floor and
        cluster factor.
    """

    clusterings: dict[tuple[str, float], Clustering] = field(default_factory=dict)
    regions: dict[tuple[str, int, float], list[ChangedRegion]] = field(default_factory=dict)


def small_clusters(
    own: ChangedPoints, floor: int, cluster_factor: float, known: SmallClusters | None = None
) -> list[ChangedRegion]:
    """``own``'s clusters of changed points of at least ``floor`` points, as regions (not to be
    changed: ``known`` may hand the same list to another caller).

    ``known`` (optional): the clusters already found in this comparison, looked up first and
    filled in with those found here; a clustering of exactly ``own``'s changed points with
    ``cluster_factor`` there is filtered, not found again.
    """
    key = (own.side.region_kind, floor, cluster_factor)
    if known is not None and key in known.regions:
        return known.regions[key]
    clustering = None
    if known is not None:
        clustering = known.clusterings.get((own.side.region_kind, cluster_factor))
    clusters, _ = find_regions(
        own.side.points,
        kind=own.side.region_kind,
        changed=own.changed,
        spacing=own.side.geometry.spacing,
        distance=own.distance,
        cluster_factor=cluster_factor,
        min_region_points=floor,
        evidence=own.evidence,
        confidence=own.confidence,
        clustering=clustering if clustering is not None and clustering.of(own.changed) else None,
    )
    if known is not None:
        known.regions[key] = clusters
    return clusters


def face_normal(points: NDArray[np.float64]) -> NDArray[np.float64]:
    """The unit normal of the plane fitted to ``points`` (shape (p, 3) -> (3,))."""
    return principal_axes(points)[2][:, 0]


def _meets_at_angle(
    face: NDArray[np.float64],
    face_normals: NDArray[np.floating],
    other: Side,
    region_points: NDArray[np.int64],
    region_tree: KDTree,
    reach: float,
    corner: bool = True,
) -> bool:
    """Whether the upright ``face`` (points, shape (p, 3); upright by its plane fit) meets the
    other cloud's ``region_points`` (indices, shape (r,); ``region_tree`` over their
    positions) at an edge: :data:`MIN_MEETING` of its points within ``reach`` of one, and
    :data:`MEETING_SHARE` of those at an upright surface at an angle to their own normals
    (``face_normals``, shape (p, 3): a cluster that is an L of two faces of a turned box has
    the plane of its larger face, while the points meeting the old face may be the other
    face's, robot warehouse 2104); or, with fewer points within ``reach``,
    :data:`MIN_MEETING` of the region's points meet it at a corner line within ``reach`` of
    both (:func:`_corner_points`, when ``corner``: a face seen only from a little off the
    corner it shares with the other)."""
    normal = face_normal(face)
    if abs(normal[2]) >= UPRIGHT_NORMAL_Z:
        return False
    distance, index = region_tree.query(face, k=1, distance_upper_bound=reach)
    meeting = np.asarray(distance).ravel() <= reach
    if np.count_nonzero(meeting) < MIN_MEETING:
        if not corner:
            return False
        met_at = _corner_points(face, normal, other, region_points, region_tree, reach)
        return met_at >= MIN_MEETING
    nearest = region_points[np.asarray(index, dtype=np.int64).ravel()[meeting]]
    met = other.geometry.normal[nearest].astype(np.float64)
    own = face_normals[meeting].astype(np.float64)
    at_angle = (np.abs(met[:, 2]) < UPRIGHT_NORMAL_Z) & (
        np.abs(np.einsum("pd,pd->p", met, own)) < EDGE_COSINE
    )
    return bool(np.mean(at_angle) >= MEETING_SHARE)


def _corner_points(
    face: NDArray[np.float64],
    normal: NDArray[np.float64],
    other: Side,
    region_points: NDArray[np.int64],
    region_tree: KDTree,
    reach: float,
) -> int:
    """How many of the other cloud's ``region_points`` (indices, shape (r,); ``region_tree``
    over their positions) lie on an upright surface at an angle to the upright ``face``
    (points, shape (p, 3); unit ``normal``, shape (3,)) whose plane meets the face's plane in a
    vertical corner line within ``reach`` of the point and of a point of the face at its
    height: a face seen only from a little off the corner it shares with the other."""
    k = min(CORNER_NEIGHBOURS, region_points.shape[0])
    distance, index = region_tree.query(face, k=k, distance_upper_bound=2.0 * reach)
    distance, index = np.asarray(distance).reshape(-1, k), np.asarray(index).reshape(-1, k)
    near = region_points[np.unique(index[distance <= 2.0 * reach])]
    if near.shape[0] == 0:
        return 0
    points = other.points[near]
    met = other.geometry.normal[near].astype(np.float64)
    along = normal[:2] / max(float(np.linalg.norm(normal[:2])), 1e-12)
    across = met[:, :2] / np.maximum(np.linalg.norm(met[:, :2], axis=1), 1e-12)[:, None]
    at_angle = (np.abs(met[:, 2]) < UPRIGHT_NORMAL_Z) & (np.abs(across @ along) < EDGE_COSINE)
    # the corner line: on the face's plane and on each point's own plane (2 x 2 per point)
    determinant = along[0] * across[:, 1] - along[1] * across[:, 0]
    ok = at_angle & (np.abs(determinant) > 1e-6)
    if not ok.any():
        return 0
    face_offset = float(along @ face.mean(axis=0)[:2])
    own_offset = np.einsum("pd,pd->p", across[ok], points[ok, :2])
    corner = np.column_stack(
        [
            (face_offset * across[ok, 1] - along[1] * own_offset) / determinant[ok],
            (along[0] * own_offset - face_offset * across[ok, 0]) / determinant[ok],
        ]
    )
    to_point = np.linalg.norm(points[ok, :2] - corner, axis=1) <= reach
    to_face = np.linalg.norm(face[None, :, :2] - corner[:, None, :], axis=2) <= reach
    level = np.abs(face[None, :, 2] - points[ok, 2][:, None]) <= reach
    return int(np.count_nonzero(to_point & (to_face & level).any(axis=1)))


def turned_faces(
    changed: tuple[ChangedPoints, ChangedPoints],
    regions: list[ChangedRegion],
    *,
    cluster_factor: float,
    min_region_points: int,
    change_threshold: float,
    known: SmallClusters | None = None,
) -> list[ChangedRegion]:
    """The clusters of changed points under ``min_region_points`` that are faces turned in
    place (module docstring), as regions.

    Parameters
    ----------
    changed : (ChangedPoints, ChangedPoints)
        The reference's and the scan's changed points.
    regions : list of ChangedRegion
        The regions kept (of both kinds): a small cluster must meet one of the other cloud's.
    cluster_factor : float
        Points closer than this many local spacings are one cluster.
    min_region_points : int
    change_threshold : float
        ``c`` (metres): a face meets a region within :data:`EDGE_FACTOR` of it.
    known : SmallClusters, optional
        The small clusters found so far (:func:`small_clusters`).

    Returns
    -------
    list of ChangedRegion
        The small clusters kept, reference's first.
    """
    floor, sides = small_face_sides(changed, min_region_points)
    kept: list[ChangedRegion] = []
    for own, other in sides:
        region_points = [r.point_indices for r in regions if r.kind == other.side.region_kind]
        if not region_points:
            continue
        other_points = np.concatenate(region_points)
        other_tree = KDTree(other.side.points[other_points])
        small = small_clusters(own, floor, cluster_factor, known)
        kept += [
            region
            for region in small
            if region.n_points < min_region_points
            and _meets_at_angle(
                own.side.points[region.point_indices],
                own.side.geometry.normal[region.point_indices],
                other.side,
                other_points,
                other_tree,
                EDGE_FACTOR * change_threshold,
                corner=own.test in CORNER_TESTS,
            )
        ]
    return kept
