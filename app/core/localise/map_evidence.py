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

A coverage-difference cluster that the other epoch nevertheless saw through (surface this epoch
lacks behind it on a good share of its points: an opened door in a wall) is a change.  The
dimensions that decide are relative to the clouds' own spacing and the change threshold, never
to a sensor's ring pattern, which voxel filters and SLAM fusion erase.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.core.localise.distance import Side
from app.core.localise.gaps import NORMAL_AGREEMENT_COSINE, PLANE_SLOPE, tangent_directions
from app.core.localise.interface import VisibilityContext, VisibilityOutcome
from app.core.localise.origin_free import BEHIND_MIN_RADIUS, UNMATCHED_FACTOR, behind_evidence
from app.core.localise.rays import STATUS_SEEN_THROUGH, STATUS_UNOBSERVED, Candidates
from app.core.localise.regions import (
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
SURFACE_REACH = 0.8
"""The other epoch's surface must extend this far (metres) from a continuing border point, in
at least :data:`SURFACE_SECTORS` directions of its plane: a floor, a wall, a ceiling, not the
edge of a slid chair's seat."""
SURFACE_SECTORS = 2
SECTORS = 8
SECTOR_HALF_ANGLE_COSINE = math.cos(math.radians(35.0))
PROBE_NEIGHBOURS = 4
COPLANAR_SHARE = 0.75
COPLANAR_SAMPLE = 256
COPLANAR_REACHES = (0.25, 0.5, 1.0, 2.0)
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


def _coplanar_sectors(
    points: NDArray[np.float64],
    normal: NDArray[np.floating],
    cloud: LocalGeometry,
    tolerance: float,
    reach: float,
) -> NDArray[np.int64]:
    """In how many of :data:`SECTORS` directions of each point's plane ``cloud`` has surface
    on that plane about ``reach`` away (between half and twice it; shapes (p, 3) -> (p,))."""
    count = points.shape[0]
    if count == 0:
        return np.zeros(0, dtype=np.int64)
    unit, directions = tangent_directions(normal, SECTORS)
    k = min(PROBE_NEIGHBOURS, cloud.points.shape[0])
    hits = np.zeros((count, SECTORS), dtype=bool)
    for sector in range(SECTORS):
        direction = directions[:, sector, :]
        _, index = cloud.tree.query(points + reach * direction, k=k)
        index = np.asarray(index).reshape(count, k)
        offset = cloud.points[index] - points[:, None, :]
        distance = np.linalg.norm(offset, axis=2)
        across = np.abs(np.einsum("pkd,pd->pk", offset, unit))
        along = np.einsum("pkd,pd->pk", offset, direction)
        agrees = np.abs(np.einsum("pkd,pd->pk", cloud.normal[index], unit))
        hits[:, sector] = (
            (distance <= 2.0 * reach)
            & (along >= SECTOR_HALF_ANGLE_COSINE * distance)
            & (along >= 0.5 * reach)
            & (across <= tolerance + PLANE_SLOPE * distance)
            & (agrees >= NORMAL_AGREEMENT_COSINE)
        ).any(axis=1)
    return hits.sum(axis=1)


def _extends(
    points: NDArray[np.float64],
    normal: NDArray[np.floating],
    cloud: LocalGeometry,
    tolerance: float,
) -> NDArray[np.bool_]:
    """Whether ``cloud`` has surface on each point's plane :data:`SURFACE_REACH` away in at
    least :data:`SURFACE_SECTORS` directions (shapes (p, 3) -> (p,))."""
    return _coplanar_sectors(points, normal, cloud, tolerance, SURFACE_REACH) >= SURFACE_SECTORS


def _coplanar_share(
    candidates: Candidates,
    labels: NDArray[np.int64],
    n_clusters: int,
    other: LocalGeometry,
    tolerance: float,
) -> NDArray[np.float64]:
    """Per cluster, the share of (up to :data:`COPLANAR_SAMPLE`) sampled candidates whose own
    plane the other epoch has within :data:`COPLANAR_REACHES` of them, in some direction.

    A patch of a continuing wall, floor or ceiling lies on the other epoch's plane almost
    everywhere; a removed object's faces do not, even where one of them is in line with a
    surface that stays (a cabinet's front above a cupboard that stays).
    """
    rng = np.random.default_rng(0)
    order = rng.permutation(labels.shape[0])
    rank = np.empty_like(order)
    ranked = order[np.argsort(labels[order], kind="stable")]
    starts = np.searchsorted(labels[ranked], np.arange(n_clusters))
    rank[ranked] = np.arange(ranked.shape[0]) - starts[labels[ranked]]
    sample = np.flatnonzero(rank < COPLANAR_SAMPLE)
    points, normal = candidates.points[sample], candidates.normal[sample]
    found = np.zeros(sample.shape[0], dtype=bool)
    for reach in COPLANAR_REACHES:
        todo = np.flatnonzero(~found)
        found[todo] = _coplanar_sectors(points[todo], normal[todo], other, tolerance, reach) >= 1
    hits = np.bincount(labels[sample], weights=found.astype(np.float64), minlength=n_clusters)
    return hits / np.maximum(np.bincount(labels[sample], minlength=n_clusters), 1)


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
    labels = cluster_labels(candidates.points, cluster_factor * candidates.spacing)
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
    # a continuing border point counts when the other epoch's surface extends well beyond it
    probe = np.flatnonzero(continues)
    continues[probe] = _extends(
        candidates.points[probe], candidates.normal[probe], other.geometry, threshold
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

    nearest = own.nearest_distance[candidates.index]
    order = np.lexsort((nearest, labels))
    starts = np.searchsorted(labels[order], np.arange(n_clusters))
    near_rank = starts + np.floor(NEAR_QUANTILE * (sizes - 1)).astype(np.int64)
    near_distance = nearest[order][near_rank]
    near_limit = max(NEAR_MIN, NEAR_FACTOR * change_threshold)
    near = near_distance <= near_limit

    coplanar_share = _coplanar_share(candidates, labels, n_clusters, other.geometry, threshold)
    continues_plainly = continuation_share >= PLAIN_CONTINUATION_SHARE
    continues_in_plane = (continuation_share >= CONTINUATION_SHARE) & (
        coplanar_share >= COPLANAR_SHARE
    )
    coverage = (continues_plainly | continues_in_plane) & (behind_share < SEE_THROUGH_SHARE)
    coverage |= ~near
    cluster_confidence = np.where(
        coverage,
        np.where(near, continuation_share, 1.0),
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
