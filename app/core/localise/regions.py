"""Connected regions of changed points and their summaries.

Changed points of each cloud are linked to neighbours closer than ``cluster_factor`` local
spacings (k-nearest-neighbour graph, sparse connected components); clusters smaller than
``min_region_points`` are noise, so the changed points are exactly the regions' points.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.localise.neighbourhoods import kernel_self_neighbours

__all__ = [
    "EVIDENCE_NAMES",
    "ChangedRegion",
    "Clustering",
    "cluster_changed",
    "cluster_labels",
    "find_regions",
    "mark_moved_surfaces",
]

CLUSTER_NEIGHBOURS = 10
EVIDENCE_NONE = 0
EVIDENCE_SEEN_EMPTY = 1
EVIDENCE_SURFACE_MOVED = 2
EVIDENCE_NO_COVERAGE = 3
EVIDENCE_NAMES = {
    EVIDENCE_SEEN_EMPTY: "seen_empty",
    EVIDENCE_SURFACE_MOVED: "surface_moved",
    EVIDENCE_NO_COVERAGE: "no_coverage",
}
"""Per-point evidence codes of change candidates (0: not a candidate), and the names regions
report."""
MOVED_GAP = 1.0
"""A removed and an added region whose boxes lie within this distance (metres) of each other
are one surface moved."""


@dataclass(frozen=True)
class ChangedRegion:
    """One connected cluster of changed points.

    Attributes
    ----------
    kind : {"added", "removed"}
        "added": scan points with no counterpart in the reference; "removed": reference points
        with no counterpart in the scan.
    point_indices : ndarray, shape (k,), int64
        Sorted indices into the scan ("added") or the reference ("removed").
    centroid, bbox_min, bbox_max : ndarray, shape (3,), float64
        Mean position and axis-aligned bounds of the points, in the reference frame.
    mean_distance, max_distance : float
        Mean and largest distance of the points to the other cloud's surface (metres).
    evidence : {"seen_empty", "surface_moved", "no_coverage"}
        Why it is reported: the other epoch saw its place empty (through, behind or beneath
        it); the surface is found again displaced nearby (a region of the other kind lies
        within :data:`MOVED_GAP`); or the other epoch did not cover it (an uncertain region:
        it does not count for the decision, its points are unobserved).
    confidence : float
        Mean confidence of its points' labels, in [0, 1] (direct evidence: 1).
    """

    kind: str
    point_indices: NDArray[np.int64]
    centroid: NDArray[np.float64]
    bbox_min: NDArray[np.float64]
    bbox_max: NDArray[np.float64]
    mean_distance: float
    max_distance: float
    evidence: str = "seen_empty"
    confidence: float = 1.0

    @property
    def n_points(self) -> int:
        """Number of points in the region."""
        return int(self.point_indices.shape[0])


@dataclass(frozen=True)
class Clustering:
    """One cloud's changed points and the connected cluster each belongs to
    (:func:`cluster_changed`).

    Attributes
    ----------
    changed_index : ndarray, shape (c,), intp
        The changed points' indices into the cloud, ascending.
    labels : ndarray, shape (c,), int
        Their cluster labels (:func:`cluster_labels`).
    """

    changed_index: NDArray[np.intp]
    labels: NDArray[np.integer]

    def of(self, changed: NDArray[np.bool_]) -> bool:
        """Whether these are the clusters of exactly the points ``changed`` (shape (n,))."""
        return np.array_equal(np.flatnonzero(changed), self.changed_index)


def cluster_changed(
    points: NDArray[np.float64],
    changed: NDArray[np.bool_],
    spacing: NDArray[np.float64],
    cluster_factor: float,
    threads: int = 1,
) -> Clustering:
    """The connected clusters of one cloud's ``changed`` points (shapes (n, 3) and (n,)), each
    linked to neighbours closer than ``cluster_factor`` of its ``spacing`` (shape (n,)); the
    links found on ``threads`` threads (:func:`cluster_labels`)."""
    changed_index = np.flatnonzero(changed)
    radius = cluster_factor * spacing[changed_index]
    return Clustering(changed_index, cluster_labels(points[changed_index], radius, threads))


def cluster_labels(
    points: NDArray[np.float64], radius: NDArray[np.float64], threads: int = 1
) -> NDArray:
    """Connected components of points linked to neighbours within their own ``radius``.

    Each point is linked to its :data:`CLUSTER_NEIGHBOURS` nearest neighbours that lie within
    its radius (a k-nearest-neighbour graph cut at the radius: on surfaces it connects what
    the full radius graph connects, at a fixed cost per point).

    Parameters
    ----------
    points : ndarray, shape (c, 3)
    radius : ndarray, shape (c,)
    threads : int
        Threads of the compiled kernel's neighbour search (the same links on any number).

    Returns
    -------
    ndarray, shape (c,), int
        Component label per point.
    """
    count = points.shape[0]
    if count <= 1:
        return np.zeros(count, dtype=np.int64)
    k = min(CLUSTER_NEIGHBOURS + 1, count)
    neighbour, linked = _links(points, radius, k, threads)
    rows = np.repeat(np.arange(count), k - 1)[linked.ravel()]
    columns = neighbour[:, 1:][linked]
    from scipy.sparse import coo_matrix  # on first use: API processes need no scipy
    from scipy.sparse.csgraph import connected_components

    graph = coo_matrix((np.ones(rows.shape[0], dtype=np.int8), (rows, columns)), (count, count))
    _, labels = connected_components(graph, directed=True, connection="weak")
    return labels


def _links(
    points: NDArray[np.float64], radius: NDArray[np.float64], k: int, threads: int = 1
) -> tuple[NDArray[np.uint32], NDArray[np.bool_]]:
    """:func:`cluster_labels`' graph: each point's ``k`` nearest (itself first; shape (c, k))
    and which of the other ``k - 1`` lie within its ``radius`` (shape (c, k - 1)).

    pykdtree's query bounded at the largest radius (a neighbour beyond it: not linked), or
    the compiled kernel's neighbours (:func:`kernel_self_neighbours`, ~30 % less CPU, the same
    neighbours) with their distances computed as pykdtree computes them, ((dx dx + dy dy) +
    dz dz), and its bound (a squared distance below the bound's square); a point whose
    neighbours' order is not unique is asked of the bounded query: the same links either way.
    """
    bound = radius.max()
    found = kernel_self_neighbours(points, k - 1, threads) if points.dtype == np.float64 else None
    if found is None:
        distance, neighbour = KDTree(points).query(points, k=k, distance_upper_bound=bound)
        return neighbour, distance[:, 1:] <= radius[:, None]
    neighbour, tie = found
    squared = np.zeros((points.shape[0], k - 1))
    for axis in range(3):
        gap = points[neighbour[:, 1:], axis] - points[:, axis, None]
        squared += gap * gap
    linked = (squared < bound * bound) & (np.sqrt(squared) <= radius[:, None])
    if tie.any():
        rows = np.flatnonzero(tie)
        distance, neighbour[rows] = KDTree(points).query(
            points[rows], k=k, distance_upper_bound=bound
        )
        linked[rows] = distance[:, 1:] <= radius[rows, None]
    return neighbour, linked


def find_regions(
    points: NDArray[np.float64],
    *,
    kind: str,
    changed: NDArray[np.bool_],
    spacing: NDArray[np.float64],
    distance: NDArray[np.float64],
    cluster_factor: float,
    min_region_points: int,
    evidence: NDArray[np.int8] | None = None,
    confidence: NDArray[np.floating] | None = None,
    clustering: Clustering | None = None,
) -> tuple[list[ChangedRegion], int]:
    """Cluster one cloud's changed points into regions of at least ``min_region_points``.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    kind : {"removed", "added"}
        Of the regions (the reference's changed points are removed, the scan's added).
    changed : ndarray, shape (n,), bool
    spacing : ndarray, shape (n,)
        The cloud's local spacing: points closer than ``cluster_factor`` spacings are linked.
    distance : ndarray, shape (n,)
        Each point's distance to the other cloud's surface.
    cluster_factor : float
    min_region_points : int
    evidence : ndarray, shape (n,), int8, optional
        Evidence code of each point (:data:`EVIDENCE_NAMES`); a region takes its points' most
        common one.  Default: seen_empty.
    confidence : ndarray, shape (n,), optional
        Each point's confidence; a region's is their mean.  Default 1.
    clustering : Clustering, optional
        The clusters of these ``changed`` points with this ``cluster_factor``, when already
        found (:func:`cluster_changed`); default: found here.

    Returns
    -------
    regions : list of ChangedRegion
    n_dropped_clusters : int
        Clusters smaller than ``min_region_points``.
    """
    if clustering is None:
        clustering = cluster_changed(points, changed, spacing, cluster_factor)
    changed_index, labels = clustering.changed_index, clustering.labels
    if labels.size == 0:
        return [], 0
    sizes = np.bincount(labels)
    order = np.argsort(labels, kind="stable")
    boundaries = np.flatnonzero(np.diff(labels[order])) + 1
    regions = []
    for members in np.split(changed_index[order], boundaries):
        if members.shape[0] < min_region_points:
            continue
        region_points = points[members]
        region_distance = distance[members]
        evidence_name = "seen_empty"
        if evidence is not None:
            codes = np.bincount(evidence[members], minlength=len(EVIDENCE_NAMES) + 1)
            codes[0] = 0
            evidence_name = EVIDENCE_NAMES.get(int(np.argmax(codes)), "seen_empty")
        regions.append(
            ChangedRegion(
                kind=kind,
                point_indices=np.sort(members).astype(np.int64),
                centroid=region_points.mean(axis=0),
                bbox_min=region_points.min(axis=0),
                bbox_max=region_points.max(axis=0),
                mean_distance=float(region_distance.mean()),
                max_distance=float(region_distance.max()),
                evidence=evidence_name,
                confidence=1.0 if confidence is None else float(np.mean(confidence[members])),
            )
        )
    return regions, int((sizes < min_region_points).sum())


def mark_moved_surfaces(
    regions: list[ChangedRegion], gap: float = MOVED_GAP
) -> list[ChangedRegion]:
    """Removed and added regions whose boxes lie within ``gap`` of each other: surface_moved.

    A moved or rotated object leaves a removed region where it stood and an added one where
    it stands; a door swung open, a wall pushed back, the same.  Uncertain regions
    (``no_coverage``) keep their evidence.

    Parameters
    ----------
    regions : list of ChangedRegion
    gap : float
        Largest distance (metres) between the two boxes.

    Returns
    -------
    list of ChangedRegion
        The same regions, in the same order.
    """
    removed = [r for r in regions if r.kind == "removed" and r.evidence != "no_coverage"]
    added = [r for r in regions if r.kind == "added" and r.evidence != "no_coverage"]
    moved: set[int] = set()
    for first in removed:
        for second in added:
            separation = np.maximum(
                0.0, np.maximum(first.bbox_min - second.bbox_max, second.bbox_min - first.bbox_max)
            )
            if float(np.linalg.norm(separation)) <= gap:
                moved.update((id(first), id(second)))
    return [
        dataclasses.replace(region, evidence="surface_moved") if id(region) in moved else region
        for region in regions
    ]
