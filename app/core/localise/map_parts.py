"""The figures the map test decides on, per surface part of one map's change candidates.

Candidates (points farther than the change threshold from the other epoch's surface) are split
into surface parts (:func:`surface_parts`); per part, :func:`part_figures` measures how its
border continues into the other epoch's surfaces, whether those surfaces carry on past it,
whether the other epoch saw through its place, and whether it is near the other epoch's
coverage at all.  :mod:`app.core.localise.map_evidence` decides on these figures.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.localise.distance import Side
from app.core.localise.gaps import NORMAL_AGREEMENT_COSINE, PLANE_SLOPE
from app.core.localise.map_planes import extends, share_on_planes
from app.core.localise.map_sides import LEVEL_NORMAL_Z, inner_sides, surface_behind
from app.core.localise.map_steps import split_offsets, split_steps
from app.core.localise.map_surround import SURROUND_SECTORS, UPRIGHT_NORMAL_Z, surrounded
from app.core.localise.origin_free import UNMATCHED_FACTOR
from app.core.localise.rays import Candidates
from app.core.localise.regions import CLUSTER_NEIGHBOURS, cluster_labels
from app.core.localise.sample_lines import continues_into
from app.core.localise.settings import GATHER_CHUNK

__all__ = [
    "PartFigures",
    "part_figures",
    "surface_parts",
    "unmatched_points",
]

BORDER_NEIGHBOURS = 16
"""Own neighbours of a candidate looked at for its cluster's border."""
MIXED_SHARE = 0.25
"""A part whose level candidates are between this share and its complement is split into
its upright and its level surfaces."""
NEAR_FACTOR = 3.0
NEAR_MIN = 1.0
"""A cluster is near the other epoch's coverage when its closest tenth of points lies within
``max(NEAR_MIN, NEAR_FACTOR * change_threshold)`` metres of the other cloud.  A removed
chair's backrest top, seen without its lower part, is 0.7-0.9 m over the floor the other
epoch saw under it: that epoch's path came near."""
NEAR_QUANTILE = 0.1


def _border_continuation(
    candidates: Candidates,
    *,
    own: Side,
    other: Side,
    is_candidate: NDArray[np.bool_],
    tolerance: float,
    change_threshold: float,
    cluster_factor: float,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Which candidates lie on their cluster's border, and which of those continue into a
    surface the other epoch has, parallel, next to them.

    Returns
    -------
    border, continues : ndarray, shape (c,), bool
    """
    count = candidates.index.shape[0]
    border = np.zeros(count, dtype=bool)
    continues = np.zeros(count, dtype=bool)
    k = min(BORDER_NEIGHBOURS + 1, own.points.shape[0])
    for start in range(0, count, GATHER_CHUNK):
        chunk = slice(start, start + GATHER_CHUNK)
        query = candidates.points[chunk]
        unit = candidates.normal[chunk].astype(np.float64)
        unit /= np.maximum(np.linalg.norm(unit, axis=1), 1e-12)[:, None]
        radius = cluster_factor * candidates.spacing[chunk]
        distance, neighbour = own.geometry.tree.query(
            query, k=k, distance_upper_bound=float(radius.max())
        )
        distance = np.asarray(distance).reshape(query.shape[0], k)
        neighbour = np.minimum(
            np.asarray(neighbour).reshape(query.shape[0], k), own.points.shape[0] - 1
        )
        outside = (distance <= radius[:, None]) & ~is_candidate[neighbour]
        border[chunk] = outside.any(axis=1)
        offset = own.points[neighbour] - query[:, None, :]
        across = np.abs(np.einsum("ckd,cd->ck", offset, unit))
        coplanar = (across <= tolerance + PLANE_SLOPE * distance) & (
            np.abs(np.einsum("ckd,cd->ck", own.geometry.normal[neighbour], unit))
            >= NORMAL_AGREEMENT_COSINE
        )
        # where the own surface carries on, the other epoch's nearest surface is parallel and
        # on it (or a line of samples in its plane): the same surface, seen by both epochs
        continues[chunk] = continues_into(
            unit,
            own.points[neighbour],
            own.nearest_index[neighbour],
            outside & coplanar,
            own.geometry,
            other.geometry,
            change_threshold,
            anchor=query,
        ).any(axis=1)
    return border, continues


def surface_parts(
    points: NDArray[np.float64],
    normal: NDArray[np.floating],
    radius: NDArray[np.float64],
    step: float | None = None,
) -> NDArray[np.int64]:
    """Connected parts of candidates that lie on one surface: neighbours within a candidate's
    ``radius`` (its :data:`~app.core.localise.regions.CLUSTER_NEIGHBOURS` nearest) are linked
    when their normals agree (:data:`~app.core.localise.gaps.NORMAL_AGREEMENT_COSINE`).

    A cluster of candidates may join a change to a coverage difference: a removed fence to
    the rough ground strips beside it, the side of a box only one path faced to the floor
    strip in the other path's shadow.  Each surface of it is judged on its own.

    Parameters
    ----------
    points, normal : ndarray, shape (c, 3)
    radius : ndarray, shape (c,)
    step : float, optional
        Split level parts of two level surfaces this far apart (:func:`split_steps`).

    Returns
    -------
    ndarray, shape (c,), int64
        Part label per candidate, ``0 .. parts - 1``.
    """
    count = points.shape[0]
    if count <= 1:
        return np.zeros(count, dtype=np.int64)
    unit = normal.astype(np.float64)
    unit /= np.maximum(np.linalg.norm(unit, axis=1), 1e-12)[:, None]
    k = min(CLUSTER_NEIGHBOURS + 1, count)
    distance, neighbour = KDTree(points).query(points, k=k, distance_upper_bound=radius.max())
    neighbour = np.minimum(neighbour[:, 1:], count - 1)
    linked = (distance[:, 1:] <= radius[:, None]) & (
        np.abs(np.einsum("ckd,cd->ck", unit[neighbour], unit)) >= NORMAL_AGREEMENT_COSINE
    )
    labels = _components(linked, neighbour, count)
    # upright or level, never both: points at a crease have normals turning gradually from
    # one surface's to the other's and chain a board to the floor it stands on.  Only a part
    # with much of both is split (rough ground has a few steep points, a fence a few flat ones)
    level = np.abs(unit[:, 2]) >= LEVEL_NORMAL_Z
    sizes = np.bincount(labels).astype(np.float64)
    level_share = np.bincount(labels, weights=level.astype(np.float64)) / sizes
    mixed = (level_share >= MIXED_SHARE) & (level_share <= 1.0 - MIXED_SHARE)
    if mixed.any():
        linked &= ~mixed[labels][:, None] | (level[neighbour] == level[:, None])
        labels = _components(linked, neighbour, count)
    labels = split_steps(points, level, linked, neighbour, labels, step)
    return split_offsets(points, unit, level, linked, neighbour, labels, step).astype(np.int64)


def _components(
    linked: NDArray[np.bool_], neighbour: NDArray[np.int64], count: int
) -> NDArray[np.int64]:
    """Connected components of the graph linking each point to its ``linked`` neighbours
    (shapes (c, k), (c, k) -> (c,))."""
    rows = np.repeat(np.arange(count), neighbour.shape[1])[linked.ravel()]
    columns = neighbour[linked]
    from scipy.sparse import coo_matrix  # on first use: API processes need no scipy
    from scipy.sparse.csgraph import connected_components

    graph = coo_matrix((np.ones(rows.shape[0], dtype=np.int8), (rows, columns)), (count, count))
    _, labels = connected_components(graph, directed=True, connection="weak")
    return labels.astype(np.int64)


@dataclass(frozen=True)
class PartFigures:
    """The figures the map test decides on, one per surface part of the candidates.

    Attributes
    ----------
    sizes : ndarray, shape (parts,), float64
        Candidates per part.
    near : ndarray, shape (parts,), bool
        The part's cluster is near the other epoch's coverage.
    continuation_share : ndarray, shape (parts,), float64
        Share of the part's border points whose surface continues into the other epoch's.
    coplanar_share : ndarray, shape (parts,), float64
        Share of its points on planes the other epoch has nearby.
    behind_share : ndarray, shape (parts,), float64
        Share of its points with surface this epoch lacks on their normal lines.
    adjoining : ndarray, shape (parts,), float64
        Its border points that the other epoch's surface adjoins at an edge.
    surround_share : ndarray, shape (parts,), float64
        Share of those where that surface carries on past the point.
    adjoined : ndarray, shape (b,), int64
        Those border points of every part (indices into the candidates).
    upright : ndarray, shape (parts,), bool
        The part is an upright face.
    counts : dict
        Point counts for the report.
    """

    sizes: NDArray[np.float64]
    near: NDArray[np.bool_]
    continuation_share: NDArray[np.float64]
    coplanar_share: NDArray[np.float64]
    behind_share: NDArray[np.float64]
    adjoining: NDArray[np.float64]
    surround_share: NDArray[np.float64]
    adjoined: NDArray[np.int64]
    upright: NDArray[np.bool_]
    counts: dict[str, Any]


def _continuation_share(
    candidates: Candidates,
    labels: NDArray[np.int64],
    n_parts: int,
    *,
    own: Side,
    other: Side,
    threshold: float,
    change_threshold: float,
    cluster_factor: float,
) -> tuple[NDArray[np.bool_], NDArray[np.float64], dict[str, int]]:
    """The candidates on their part's border, and per part the share of its border points that
    continue into a surface the other epoch has and that extends well beyond them."""
    is_candidate = np.zeros(own.points.shape[0], dtype=bool)
    is_candidate[candidates.index] = True
    border, continues = _border_continuation(
        candidates,
        own=own,
        other=other,
        is_candidate=is_candidate,
        tolerance=threshold,
        change_threshold=change_threshold,
        cluster_factor=cluster_factor,
    )
    # a continuing border point counts when the other epoch's surface extends well beyond it,
    # on the point's own plane or, where its own normal leans (a noisy far wall band of an RGB-D
    # map, some 15 degrees off under the ceiling), on the plane of the other epoch's surface
    probe = np.flatnonzero(continues)
    continues[probe] = extends(
        candidates.points[probe], candidates.normal[probe], other.geometry, threshold, lines=True
    )
    probe = probe[~continues[probe]]
    continues[probe] = extends(
        candidates.points[probe],
        other.geometry.normal[own.nearest_index[candidates.index[probe]]],
        other.geometry,
        threshold,
    )
    border_count = np.bincount(labels, weights=border.astype(np.float64), minlength=n_parts)
    continuing = np.bincount(labels, weights=continues.astype(np.float64), minlength=n_parts)
    counts = {"map_border_points": int(border.sum()), "map_continuing_points": int(continues.sum())}
    return border, continuing / np.maximum(border_count, 1.0), counts


def _near_coverage(
    candidates: Candidates,
    labels: NDArray[np.int64],
    n_parts: int,
    *,
    own: Side,
    change_threshold: float,
    cluster_factor: float,
) -> NDArray[np.bool_]:
    """Per part, whether its whole connected cluster is near the other epoch's coverage (a
    removed box's top is far from the floor, its sides are not)."""
    clusters = cluster_labels(candidates.points, cluster_factor * candidates.spacing)
    cluster_sizes = np.bincount(clusters).astype(np.float64)
    nearest = own.nearest_distance[candidates.index]
    order = np.lexsort((nearest, clusters))
    starts = np.searchsorted(clusters[order], np.arange(cluster_sizes.shape[0]))
    near_rank = starts + np.floor(NEAR_QUANTILE * (cluster_sizes - 1)).astype(np.int64)
    near_limit = max(NEAR_MIN, NEAR_FACTOR * change_threshold)
    cluster_near = nearest[order][near_rank] <= near_limit
    near = np.zeros(n_parts, dtype=bool)
    near[labels] = cluster_near[clusters]
    return near


def _adjoining_surfaces(
    candidates: Candidates,
    labels: NDArray[np.int64],
    n_parts: int,
    border: NDArray[np.bool_],
    *,
    other: Side,
    other_unmatched: NDArray[np.bool_],
    threshold: float,
    change_threshold: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """Per part, how many border points the other epoch's surface adjoins at an edge and the
    share of those where it carries on past the point
    (:func:`~app.core.localise.map_surround.surrounded`), and those border points (indices into
    the candidates).

    A part all of whose adjoining border points have the adjoining surface wholly under them
    (:func:`~app.core.localise.map_planes.holds_up`) stands on it: that surface is no face of
    its object, as a level support that ends at it is none
    (:func:`~app.core.localise.map_surround._supports`), and the part has no adjoining border
    point."""
    probe = np.flatnonzero(border)
    # the parts whose border has surface this epoch lacks nearest: which side is open?
    wanted = np.zeros(n_parts, dtype=bool)
    if probe.shape[0]:
        _, nearest = other.geometry.tree.query(candidates.points[probe], k=1)
        wanted[labels[probe][other_unmatched[np.asarray(nearest).ravel()]]] = True
    inward = inner_sides(
        candidates.points, candidates.normal, labels, wanted, other, other_unmatched
    )
    adjoining_points, surrounded_points, under = surrounded(
        candidates.points[probe],
        candidates.normal[probe],
        other.geometry,
        other_unmatched,
        threshold,
        change_threshold,
        inward[probe],
    )
    on_top = np.bincount(labels[probe], weights=adjoining_points & ~under, minlength=n_parts)
    adjoining_points &= on_top[labels[probe]] > 0
    adjoining = np.bincount(
        labels[probe], weights=adjoining_points.astype(np.float64), minlength=n_parts
    )
    carried_on = adjoining_points & (surrounded_points >= SURROUND_SECTORS)
    surround_share = np.bincount(
        labels[probe], weights=carried_on.astype(np.float64), minlength=n_parts
    ) / np.maximum(adjoining, 1.0)
    return adjoining, surround_share, probe[adjoining_points]


def unmatched_points(
    own: Side, other: Side, threshold: float, change_threshold: float
) -> NDArray[np.bool_]:
    """The other cloud's points that this one lacks: no own point within a couple of spacings
    (dense maps), or within the change threshold (sparse clouds); shape (m,), bool."""
    return other.nearest_distance > np.minimum(
        UNMATCHED_FACTOR * np.maximum(own.geometry.spacing[other.nearest_index], threshold),
        change_threshold,
    )


def part_figures(
    candidates: Candidates,
    labels: NDArray[np.int64],
    *,
    own: Side,
    other: Side,
    other_unmatched: NDArray[np.bool_],
    threshold: float,
    change_threshold: float,
    cluster_factor: float,
) -> PartFigures:
    """The figures of each surface part (``labels``: :func:`surface_parts`) of ``own``'s
    candidates against the other epoch (parameters as :func:`map_test`'s)."""
    n_parts = int(labels.max()) + 1
    sizes = np.bincount(labels, minlength=n_parts).astype(np.float64)
    border, continuation_share, counts = _continuation_share(
        candidates,
        labels,
        n_parts,
        own=own,
        other=other,
        threshold=threshold,
        change_threshold=change_threshold,
        cluster_factor=cluster_factor,
    )
    behind = surface_behind(candidates.points, candidates.normal, other, other_unmatched)
    adjoining, surround_share, adjoined = _adjoining_surfaces(
        candidates,
        labels,
        n_parts,
        border,
        other=other,
        other_unmatched=other_unmatched,
        threshold=threshold,
        change_threshold=change_threshold,
    )
    vertical = np.abs(candidates.normal[:, 2]).astype(np.float64)
    near = _near_coverage(
        candidates,
        labels,
        n_parts,
        own=own,
        change_threshold=change_threshold,
        cluster_factor=cluster_factor,
    )
    return PartFigures(
        sizes=sizes,
        near=near,
        continuation_share=continuation_share,
        coplanar_share=share_on_planes(
            candidates, labels, n_parts, other.geometry, threshold, change_threshold
        ),
        behind_share=np.bincount(labels, weights=behind.astype(np.float64), minlength=n_parts)
        / np.maximum(sizes, 1.0),
        adjoining=adjoining,
        surround_share=surround_share,
        adjoined=adjoined,
        # a side: an upright face (a top, seen from any path above it, is left to other rules)
        upright=np.bincount(labels, weights=vertical, minlength=n_parts) / np.maximum(sizes, 1.0)
        < UPRIGHT_NORMAL_Z,
        counts=counts,
    )
