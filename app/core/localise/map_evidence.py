"""The map test: change evidence for fused maps without sensor positions.

Handheld RGB-D maps, mobile laser scanning and robot SLAM maps are fused from many views and
voxel-filtered: there is no station to cast rays from and no ring pattern left.  A change
candidate (a point farther than the change threshold from the other epoch's surface) is then
judged by the geometry the two epochs share, one cluster of candidates at a time:

- **Coverage difference** (``no_coverage``): the cluster lies on a surface that continues,
  unmoved, in the other epoch: along its border, its own surface carries on into points that
  the other epoch matched, with the other epoch's surface there parallel to it, and the other
  epoch's surface extends well beyond (a floor or ceiling patch one path reached and the other
  did not, the wall behind a cabinet that hid it from the other epoch's views).  A removed
  object's faces meet the floor or wall at an angle: their border continues into nothing the
  other epoch has parallel.  A cluster is also a coverage difference when the other epoch has
  no surface anywhere near it (a room the other path never entered).
- **Seen empty** (``seen_empty``): otherwise, when the other epoch has surface that this epoch
  lacks on the normal lines through the cluster (the floor under a removed chair, the wall
  behind a removed board, seen now that the object is gone), or its surface all around.

- **An unseen side** (``no_coverage``): an upright part whose border meets the other epoch's
  surfaces at an edge (the object's top, the floor in front of it), where those surfaces end
  at the part instead of carrying on past it, and where the other epoch has no surface that
  this one lacks: the side of an object standing in both epochs that only this epoch's path
  faced.  Where the other epoch saw the place of a removed or added object, its floor, desk
  top or wall carries on under it, or is surface this epoch lacks (the object hid it).

Candidates are judged a surface part at a time (:func:`surface_parts`: connected candidates
whose normals agree), so that a change joined to a coverage difference (a removed fence to the
rough ground strips beside it, an unseen side to the floor strip in the other path's shadow) is
split; whether a part is near the other epoch's coverage is judged on its whole cluster.

A coverage-difference cluster that the other epoch nevertheless saw through (surface this epoch
lacks behind it on a good share of its points: an opened door in a wall) is a change; surface
in a narrow gap of this epoch's own does not count (the far face of a rack, each path having
seen its own aisle's face).  The
dimensions that decide are relative to the clouds' own spacing and the change threshold, never
to a sensor's ring pattern, which voxel filters and SLAM fusion erase.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from app.core.localise.distance import Side
from app.core.localise.gaps import NORMAL_AGREEMENT_COSINE, PLANE_SLOPE, tangent_directions
from app.core.localise.interface import VisibilityContext, VisibilityOutcome
from app.core.localise.map_planes import SECTORS, coplanar_sectors, extends, share_on_planes
from app.core.localise.origin_free import (
    BEHIND_MAX_RADIUS,
    BEHIND_MIN_RADIUS,
    UNMATCHED_FACTOR,
    behind_evidence,
)
from app.core.localise.rays import STATUS_SEEN_THROUGH, STATUS_UNOBSERVED, Candidates
from app.core.localise.regions import (
    CLUSTER_NEIGHBOURS,
    EVIDENCE_NO_COVERAGE,
    EVIDENCE_SEEN_EMPTY,
    cluster_labels,
)
from app.core.localise.settings import GATHER_CHUNK
from app.core.localise.surface import LocalGeometry

__all__ = ["MapEvidence", "MapTest", "map_test"]


BORDER_NEIGHBOURS = 16
"""Own neighbours of a candidate looked at for its cluster's border."""
PLAIN_CONTINUATION_SHARE = 0.6
"""A cluster is a coverage difference when this share of its border points continues into a
surface the other epoch has (and no see-through evidence overrides it).  A removed object's
border continues into nothing parallel (its faces meet the floor and walls at an angle)."""
CONTINUATION_SHARE = 0.3
"""A patch of a wall or ceiling also meets the room's corners, so half its border may not
continue: from this share on, it is a coverage difference when most of its points also lie on
planes the other epoch has nearby (:data:`COPLANAR_SHARE`)."""
COPLANAR_SHARE = 0.75
SURROUND_NEIGHBOURS = 32
"""The other epoch's points looked at around a border point's foot on its adjoining surface."""
SURROUND_REACH = 0.5
"""Metres: farther points of the adjoining surface say nothing about the border point."""
ADJOINING_FACTOR = 2.0
"""The other epoch's surface adjoins a border point within this many change thresholds."""
SURROUND_SECTORS = 6
"""The adjoining surface carries on past a border point when it lies in this many of
:data:`SECTORS` directions around the point's foot."""
SURROUND_SHARE = 0.1
"""An upright part is an unseen side when less than this share of its adjoining border points
has the other epoch's surface carrying on past them (or surface this epoch lacks)."""
EDGE_COSINE = math.cos(math.radians(60.0))
"""A surface adjoins a border point at an edge when the normals' cosine is below this."""
UPRIGHT_NORMAL_Z = 0.5
"""A part is upright (a side) when its normals' mean vertical component is below this."""
MIN_ADJOINING = 5
"""Fewer adjoining border points than this say nothing about a part."""
SEE_THROUGH_SHARE = 0.6
"""A coverage-difference cluster is still a change when this share of its points has the
other epoch's surface, missing from this epoch, on its normal line within
:data:`SEE_THROUGH_REACH`."""
SEE_THROUGH_REACH = 1.2
"""Farther along the normal line, the other epoch's unmatched surface is as likely another
coverage difference (the ceiling a path saw above a floor patch the other path saw) as what
stood in front of or behind the cluster."""
SPARSE_PROBE_FACTOR = 1.5
"""The see-through probes' balls are at least this many of the other cloud's median spacings
wide (a sparse cloud's surface is found between its samples)."""
GAP_REACH = 0.25
GAP_SECTORS = 6
"""The other epoch's point lies in a narrow gap of this epoch's surface when this epoch has
that surface on its plane about :data:`GAP_REACH` away in this many of :data:`SECTORS`
directions."""
NEAR_FACTOR = 3.0
NEAR_MIN = 0.5
"""A cluster is near the other epoch's coverage when its closest tenth of points lies within
``max(NEAR_MIN, NEAR_FACTOR * change_threshold)`` metres of the other cloud."""
NEAR_QUANTILE = 0.1


@dataclass(frozen=True)
class MapEvidence:
    """What the map test found for one cloud's candidates.

    Attributes
    ----------
    status : ndarray, shape (c,), int8
        STATUS_SEEN_THROUGH (changed) or STATUS_UNOBSERVED (a coverage difference).
    evidence : ndarray, shape (c,), int8
        EVIDENCE_SEEN_EMPTY or EVIDENCE_NO_COVERAGE.
    confidence : ndarray, shape (c,), float32
        Confidence in the candidate's cluster's verdict, in [0, 1].
    counts : dict
        JSON-serialisable figures for the report.
    """

    status: NDArray[np.int8]
    evidence: NDArray[np.int8]
    confidence: NDArray[np.float32]
    counts: dict[str, Any]


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
    other_normal = other.geometry.normal
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
        # on it: the same surface, seen by both epochs
        match = own.nearest_index[neighbour]
        parallel = (
            np.abs(np.einsum("ckd,cd->ck", other_normal[match], unit)) >= NORMAL_AGREEMENT_COSINE
        )
        on_it = (
            np.abs(np.einsum("ckd,cd->ck", other.points[match] - own.points[neighbour], unit))
            <= change_threshold
        )
        continues[chunk] = (outside & coplanar & parallel & on_it).any(axis=1)
    return border, continues


def surface_parts(
    points: NDArray[np.float64], normal: NDArray[np.floating], radius: NDArray[np.float64]
) -> NDArray[np.int64]:
    """Connected parts of candidates that lie on one surface: neighbours within a candidate's
    ``radius`` (its :data:`~app.core.localise.regions.CLUSTER_NEIGHBOURS` nearest) are linked
    when their normals agree (:data:`~app.core.localise.gaps.NORMAL_AGREEMENT_COSINE`).

    A cluster of candidates may join a change to a coverage difference: a removed fence to
    the rough ground strips beside it, the side of a box only one path faced to the floor
    strip in the other path's shadow.  Each surface of it is judged on its own.

    Parameters
    ----------
    points : ndarray, shape (c, 3)
    normal : ndarray, shape (c, 3)
    radius : ndarray, shape (c,)

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
    rows = np.repeat(np.arange(count), k - 1)[linked.ravel()]
    columns = neighbour[linked]
    graph = coo_matrix((np.ones(rows.shape[0], dtype=np.int8), (rows, columns)), (count, count))
    _, labels = connected_components(graph, directed=True, connection="weak")
    return labels.astype(np.int64)


def _surrounded(
    points: NDArray[np.float64],
    own_normal: NDArray[np.floating],
    other: LocalGeometry,
    other_unmatched: NDArray[np.bool_],
    tolerance: float,
    change_threshold: float,
) -> tuple[NDArray[np.bool_], NDArray[np.int64]]:
    """Whether the other epoch's surface adjoins each border point at an edge, and in how
    many directions it carries on past the point.

    The other epoch's nearest surface (within :data:`ADJOINING_FACTOR` change thresholds, at
    an angle to the point's own: :data:`EDGE_COSINE`) is taken as the plane of its nearest
    point; the point is projected onto it, and that plane's points around the projection (the
    :data:`SURROUND_NEIGHBOURS` nearest within :data:`SURROUND_REACH`) are sorted into
    :data:`SECTORS` directions.  Where the other epoch saw the place of a removed or added
    object, its floor, desk top or wall carries on under it: the directions are all taken (and
    where that surface is one this epoch lacks, the object hid it: all directions count).
    Where the object stands in both epochs and only this epoch faced one of its sides, the
    other epoch's surfaces next to that side (the object's top, the floor in front of it) end
    at it: half the directions are empty.

    Parameters
    ----------
    points : ndarray, shape (b, 3)
    own_normal : ndarray, shape (b, 3)
        The points' own surface normals.
    other : LocalGeometry
    other_unmatched : ndarray, shape (m,), bool
        The other epoch's points that this epoch lacks.
    tolerance, change_threshold : float
        The plane tolerance and the change threshold (metres).

    Returns
    -------
    adjoining : ndarray, shape (b,), bool
        Whether the other epoch has a surface meeting the point's at an edge next to it.
    sectors : ndarray, shape (b,), int64
        In how many of :data:`SECTORS` directions that surface carries on past the point.
    """
    count = points.shape[0]
    adjoining = np.zeros(count, dtype=bool)
    surrounded = np.zeros(count, dtype=np.int64)
    if count == 0:
        return adjoining, surrounded
    k = min(SURROUND_NEIGHBOURS, other.points.shape[0])
    for start in range(0, count, GATHER_CHUNK):
        chunk = slice(start, start + GATHER_CHUNK)
        query = points[chunk]
        distance, index = other.tree.query(query, k=k)
        distance = np.asarray(distance).reshape(query.shape[0], k)
        index = np.asarray(index).reshape(query.shape[0], k)
        nearest = index[:, 0]
        unit = other.normal[nearest].astype(np.float64)
        height = np.einsum("cd,cd->c", query - other.points[nearest], unit)
        # only a surface meeting the point's own at an edge adjoins it: one parallel to it
        # is a gap in a surface both have, or a surface under or over it
        across = (
            np.abs(np.einsum("cd,cd->c", own_normal[chunk].astype(np.float64), unit)) < EDGE_COSINE
        )
        adjoining[chunk] = (np.abs(height) <= ADJOINING_FACTOR * change_threshold) & across
        foot = query - height[:, None] * unit
        offset = other.points[index] - foot[:, None, :]
        along = np.linalg.norm(offset, axis=2)
        on_plane = (
            (distance <= SURROUND_REACH)
            & (np.abs(np.einsum("ckd,cd->ck", offset, unit)) <= tolerance + PLANE_SLOPE * along)
            & (
                np.abs(np.einsum("ckd,cd->ck", other.normal[index].astype(np.float64), unit))
                >= NORMAL_AGREEMENT_COSINE
            )
        )
        _, directions = tangent_directions(unit, 4)
        first, second = directions[:, 0, :], directions[:, 1, :]
        angle = np.arctan2(
            np.einsum("ckd,cd->ck", offset, second), np.einsum("ckd,cd->ck", offset, first)
        )
        sector = np.floor((angle + math.pi) / (2.0 * math.pi) * SECTORS).astype(np.int64)
        sector = np.clip(sector, 0, SECTORS - 1)
        taken = np.zeros((query.shape[0], SECTORS), dtype=bool)
        rows = np.broadcast_to(np.arange(query.shape[0])[:, None], sector.shape)
        taken[rows[on_plane], sector[on_plane]] = True
        surrounded[chunk] = taken.sum(axis=1)
        # a surface that this epoch lacks next to the point: the object hid it here
        surrounded[chunk][other_unmatched[nearest]] = SECTORS
    return adjoining, surrounded


def _past_narrow_gaps(
    candidates: Candidates,
    recheck: NDArray[np.int64],
    labels: NDArray[np.int64],
    behind_share: NDArray[np.float64],
    *,
    own: Side,
    other: Side,
    other_unmatched: NDArray[np.bool_],
    tolerance: float,
) -> NDArray[np.float64]:
    """Per part, the share of candidates the other epoch saw through, counting only surface
    that is not a narrow gap of this epoch's (recomputed on the ``recheck`` candidates' parts).

    Behind a narrow gap of a surface this epoch has all around it (:data:`GAP_REACH`,
    :data:`GAP_SECTORS`: the far face of a rack, each epoch's path seeing its own aisle's
    face), the other epoch saw nothing through the candidate's place: it saw the far side.
    """
    share = behind_share.copy()
    if recheck.shape[0] == 0:
        return share
    unmatched = np.flatnonzero(other_unmatched)
    reach = SEE_THROUGH_REACH + BEHIND_MAX_RADIUS
    distance, _ = KDTree(candidates.points[recheck]).query(
        other.points[unmatched], k=1, distance_upper_bound=reach
    )
    unmatched = unmatched[np.asarray(distance).ravel() <= reach]
    gap = np.zeros(other_unmatched.shape[0], dtype=bool)
    gap[unmatched] = (
        coplanar_sectors(
            other.points[unmatched],
            other.geometry.normal[unmatched],
            own.geometry,
            tolerance,
            GAP_REACH,
        )
        >= GAP_SECTORS
    )
    behind = behind_evidence(
        candidates.points[recheck],
        candidates.normal[recheck],
        other_points=other.points,
        other_normal=other.geometry.normal,
        other_unmatched=other_unmatched & ~gap,
        max_reach=SEE_THROUGH_REACH,
        min_radius=max(
            BEHIND_MIN_RADIUS, SPARSE_PROBE_FACTOR * float(np.median(other.geometry.spacing))
        ),
    )
    parts = np.unique(labels[recheck])
    hits = np.bincount(labels[recheck], weights=behind.astype(np.float64), minlength=share.shape[0])
    sizes = np.bincount(labels[recheck], minlength=share.shape[0])
    share[parts] = hits[parts] / np.maximum(sizes[parts], 1)
    return share


def map_test(
    candidates: Candidates,
    *,
    own: Side,
    other: Side,
    threshold: float,
    change_threshold: float,
    cluster_factor: float,
) -> MapEvidence:
    """Judge one fused map's change candidates against the other epoch's map.

    Parameters
    ----------
    candidates : Candidates
        ``own``'s change candidates.
    own, other : Side
        The candidates' cloud and the other one (no origins needed).
    threshold : float
        ``tau``: the plane tolerance (metres).
    change_threshold : float
        The change threshold ``c`` (metres): a surface within it is the same surface.
    cluster_factor : float
        Candidates closer than this many local spacings form one cluster.

    Returns
    -------
    MapEvidence
    """
    count = candidates.index.shape[0]
    status = np.full(count, STATUS_SEEN_THROUGH, dtype=np.int8)
    evidence = np.full(count, EVIDENCE_SEEN_EMPTY, dtype=np.int8)
    confidence = np.ones(count, dtype=np.float32)
    counts: dict[str, Any] = {"map_clusters": 0, "map_coverage_clusters": 0}
    if count == 0:
        return MapEvidence(status, evidence, confidence, counts)
    is_candidate = np.zeros(own.points.shape[0], dtype=bool)
    is_candidate[candidates.index] = True
    labels = surface_parts(
        candidates.points, candidates.normal, cluster_factor * candidates.spacing
    )
    n_clusters = int(labels.max()) + 1
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
        candidates.points[probe], candidates.normal[probe], other.geometry, threshold
    )
    probe = probe[~continues[probe]]
    continues[probe] = extends(
        candidates.points[probe],
        other.geometry.normal[own.nearest_index[candidates.index[probe]]],
        other.geometry,
        threshold,
    )
    border_count = np.bincount(labels, weights=border.astype(np.float64), minlength=n_clusters)
    continuing = np.bincount(labels, weights=continues.astype(np.float64), minlength=n_clusters)
    continuation_share = continuing / np.maximum(border_count, 1.0)

    # the other cloud's points that this one lacks: no own point within a couple of spacings
    # (dense maps), or within the change threshold (sparse clouds)
    other_unmatched = other.nearest_distance > np.minimum(
        UNMATCHED_FACTOR * np.maximum(own.geometry.spacing[other.nearest_index], threshold),
        change_threshold,
    )
    behind = behind_evidence(
        candidates.points,
        candidates.normal,
        other_points=other.points,
        other_normal=other.geometry.normal,
        other_unmatched=other_unmatched,
        max_reach=SEE_THROUGH_REACH,
        min_radius=max(
            BEHIND_MIN_RADIUS, SPARSE_PROBE_FACTOR * float(np.median(other.geometry.spacing))
        ),
    )
    sizes = np.bincount(labels, minlength=n_clusters).astype(np.float64)
    behind_share = np.bincount(labels, weights=behind.astype(np.float64), minlength=n_clusters)
    behind_share /= np.maximum(sizes, 1.0)

    # near the other epoch's coverage: judged on the whole connected cluster (a removed
    # box's top is far from the floor, its sides are not)
    clusters = cluster_labels(candidates.points, cluster_factor * candidates.spacing)
    cluster_sizes = np.bincount(clusters).astype(np.float64)
    nearest = own.nearest_distance[candidates.index]
    order = np.lexsort((nearest, clusters))
    starts = np.searchsorted(clusters[order], np.arange(cluster_sizes.shape[0]))
    near_rank = starts + np.floor(NEAR_QUANTILE * (cluster_sizes - 1)).astype(np.int64)
    near_limit = max(NEAR_MIN, NEAR_FACTOR * change_threshold)
    cluster_near = nearest[order][near_rank] <= near_limit
    near = np.zeros(n_clusters, dtype=bool)
    near[labels] = cluster_near[clusters]

    coplanar_share = share_on_planes(candidates, labels, n_clusters, other.geometry, threshold)
    probe = np.flatnonzero(border)
    adjoining_points, surrounded_points = _surrounded(
        candidates.points[probe],
        candidates.normal[probe],
        other.geometry,
        other_unmatched,
        threshold,
        change_threshold,
    )
    adjoining = np.bincount(
        labels[probe], weights=adjoining_points.astype(np.float64), minlength=n_clusters
    )
    surround_share = np.bincount(
        labels[probe],
        weights=(adjoining_points & (surrounded_points >= SURROUND_SECTORS)).astype(np.float64),
        minlength=n_clusters,
    ) / np.maximum(adjoining, 1.0)
    # the other epoch's surfaces next to the cluster end at it: a side of an object that stands
    # in both epochs, faced by this epoch's path only
    # a side: an upright face (a top, seen from any path above it, is left to the other rules)
    upright = (
        np.bincount(
            labels, weights=np.abs(candidates.normal[:, 2]).astype(np.float64), minlength=n_clusters
        )
        / np.maximum(sizes, 1.0)
        < UPRIGHT_NORMAL_Z
    )
    unseen_side = upright & (adjoining >= MIN_ADJOINING) & (surround_share < SURROUND_SHARE)
    continues_plainly = continuation_share >= PLAIN_CONTINUATION_SHARE
    continues_in_plane = (continuation_share >= CONTINUATION_SHARE) & (
        coplanar_share >= COPLANAR_SHARE
    )
    see_through_share = _past_narrow_gaps(
        candidates,
        np.flatnonzero(
            ((continues_plainly | continues_in_plane) & (behind_share >= SEE_THROUGH_SHARE))[labels]
        ),
        labels,
        behind_share,
        own=own,
        other=other,
        other_unmatched=other_unmatched,
        tolerance=threshold,
    )
    coverage = (continues_plainly | continues_in_plane) & (see_through_share < SEE_THROUGH_SHARE)
    coverage |= ~near | (unseen_side & (behind_share < SEE_THROUGH_SHARE))
    cluster_confidence = np.where(
        coverage,
        np.where(
            near,
            np.maximum(continuation_share, np.where(unseen_side, 1.0 - surround_share, 0.0)),
            1.0,
        ),
        np.clip(1.0 - continuation_share, 0.0, 1.0)
        * np.clip(0.5 + behind_share / (2 * SEE_THROUGH_SHARE), 0.0, 1.0),
    )
    status[coverage[labels]] = STATUS_UNOBSERVED
    evidence[coverage[labels]] = EVIDENCE_NO_COVERAGE
    confidence[:] = cluster_confidence[labels]
    counts.update(
        map_clusters=n_clusters,
        map_coverage_clusters=int(coverage.sum()),
        map_far_clusters=int((~near).sum()),
        map_border_points=int(border.sum()),
        map_continuing_points=int(continues.sum()),
        map_unseen_side_clusters=int((unseen_side & coverage).sum()),
        map_coplanar_share_median=float(np.median(coplanar_share)) if n_clusters else 0.0,
    )
    return MapEvidence(status, evidence, confidence, counts)


class MapTest:
    """The map test as a visibility test (``name = "maps"``)."""

    name = "maps"

    def __call__(
        self, candidates: Candidates, *, own: Side, other: Side, context: VisibilityContext
    ) -> VisibilityOutcome:
        """:func:`map_test` of ``own``'s candidates."""
        found = map_test(
            candidates,
            own=own,
            other=other,
            threshold=context.threshold,
            change_threshold=context.change_threshold,
            cluster_factor=context.settings["cluster_factor"],
        )
        return VisibilityOutcome(
            status=found.status,
            confidence=found.confidence,
            report=dict(found.counts),
            evidence=found.evidence,
        )
