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
  behind a removed board, seen now that the object is gone), or its surface all around.  An
  upright part whose first level surface of the other epoch straight under it is surface this
  epoch lacks stands on what it hides (the seat under a backrest turned onto it, the floor
  under an added box): the other epoch saw its place empty, whether or not its surface seems
  to continue or its border to meet the other epoch's faces
  (:func:`~app.core.localise.map_verdict.part_verdict`).

- **An unseen face** (``no_coverage``,
  :func:`~app.core.localise.map_shared.unseen_faces`): a part whose border meets the other
  epoch's surfaces at an edge (the object's top or other sides), where those surfaces
  end at the part instead of carrying on past it, and where the other epoch has no surface
  that this one lacks: the side of an object standing in both epochs that only this epoch's
  path faced, or its top that only this epoch's path looked down on.  Where the other epoch
  saw the place of a removed or added object, its floor, desk top or wall carries on under
  it, or is surface this epoch lacks (the object hid it).  The other epoch's surface behind
  an upright side overrides it (a wall a removed board hid), unless it is the far face of the
  same object, seen from the far side only
  (:func:`~app.core.localise.map_faces.far_faces`: the object's top and sides join the two
  faces and end at both).

Candidates are judged a surface part at a time (:func:`surface_parts`), so that a change
joined to a coverage difference is split; whether a part is near the other epoch's coverage is
judged on its whole cluster.

A coverage-difference cluster that the other epoch nevertheless saw through (surface this epoch
lacks behind it on a good share of its points: an opened door in a wall) is a change; surface
in a narrow gap of this epoch's own does not count (the far face of a rack, each path having
seen its own aisle's face), nor, for a level cluster, surface over it: it hid the cluster
(:func:`~app.core.localise.map_shared.seen_through`).  The
dimensions that decide are relative to the clouds' own spacing and the change threshold, never
to a sensor's ring pattern, which voxel filters and SLAM fusion erase.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.localise.distance import Side
from app.core.localise.gaps import NORMAL_AGREEMENT_COSINE
from app.core.localise.interface import FaceBorder, VisibilityContext, VisibilityOutcome
from app.core.localise.map_blind import seen_round, settled_coverage
from app.core.localise.map_bodies import hollow_sides
from app.core.localise.map_faces import EDGE_FACTOR, far_faces
from app.core.localise.map_fragments import fragment_hosts
from app.core.localise.map_lines import line_gap_share
from app.core.localise.map_outlines import outline_gap_share
from app.core.localise.map_parts import part_figures, surface_parts, unmatched_points
from app.core.localise.map_planes import (
    coplanar_sectors,
    first_level_surface_marked,
    level_surface_below,
    part_sampling_gap,
)
from app.core.localise.map_rims import rim_gap_share
from app.core.localise.map_scale import metric_candidates, metric_planes, metric_side
from app.core.localise.map_shared import (
    LAYER_FACTOR,
    seen_through,
    strip_sides,
    unseen_faces,
)
from app.core.localise.map_sides import SEE_THROUGH_REACH, SPARSE_PROBE_FACTOR, near_candidates
from app.core.localise.map_supports import map_statuses
from app.core.localise.map_tops import with_held_tops
from app.core.localise.map_verdict import GAP_SHARE, PLAIN_CONTINUATION_SHARE, part_verdict
from app.core.localise.origin_free import BEHIND_MIN_RADIUS
from app.core.localise.rays import STATUS_SEEN_THROUGH, Candidates

__all__ = ["MapEvidence", "MapTest", "map_test", "unseen_faces"]


GAP_REACH = 0.25
GAP_SECTORS = 6
"""The other epoch's point lies in a narrow gap of this epoch's surface when this epoch has
that surface on its plane about :data:`GAP_REACH` away in this many of :data:`SECTORS`
directions."""


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
    faces : FaceBorder or None
        The candidates that are coverage differences as unseen faces only, and their border
        points that the other epoch's surface meets
        (:func:`~app.core.localise.map_agreement.faces_meeting_changes` reads them).
    """

    status: NDArray[np.int8]
    evidence: NDArray[np.int8]
    confidence: NDArray[np.float32]
    counts: dict[str, Any]
    faces: FaceBorder | None


def _share_per_part(
    part: NDArray[np.int64], hit: NDArray[np.generic], share: NDArray[np.float64]
) -> NDArray[np.float64]:
    """``share`` (shape (parts,)) with each part that has a point in ``part`` (shape (m,)) set
    to the share of its points whose ``hit`` (shape (m,), bool or weight) holds; others kept."""
    parts = np.unique(part)
    hits = np.bincount(part, weights=np.asarray(hit, dtype=np.float64), minlength=share.shape[0])
    sizes = np.bincount(part, minlength=share.shape[0])
    share[parts] = hits[parts] / np.maximum(sizes[parts], 1)
    return share


def _probed_share(
    labels: NDArray[np.int64],
    recheck: NDArray[np.bool_],
    probe: Callable[[NDArray[np.int64]], NDArray[np.generic]],
) -> NDArray[np.float64]:
    """Per part marked in ``recheck`` (shape (parts,); 0 elsewhere), the share of its candidates
    for which ``probe`` (given the candidates' indices, shape (m,)) holds; no probe without any."""
    chosen = np.flatnonzero(recheck[labels])
    share = np.zeros(recheck.shape[0])
    if chosen.shape[0] == 0:
        return share
    return _share_per_part(labels[chosen], probe(chosen), share)


def _probe_radius(other: Side) -> float:
    """Radius of the probes straight down into ``other``'s surface: its sampling, not less than
    :data:`BEHIND_MIN_RADIUS`."""
    return max(BEHIND_MIN_RADIUS, SPARSE_PROBE_FACTOR * float(np.median(other.geometry.spacing)))


def _narrow_gaps(
    candidates: Candidates,
    recheck: NDArray[np.int64],
    *,
    own: Side,
    other: Side,
    other_unmatched: NDArray[np.bool_],
    tolerance: float,
) -> NDArray[np.bool_]:
    """The other cloud's unmatched points near the ``recheck`` candidates that lie in a narrow
    gap of this epoch's surface (shape (m,), bool).

    Behind a narrow gap of a surface this epoch has all around it (:data:`GAP_REACH`,
    :data:`GAP_SECTORS`: the far face of a rack, each epoch's path seeing its own aisle's
    face), the other epoch saw nothing through the candidate's place: it saw the far side.
    """
    gap = np.zeros(other_unmatched.shape[0], dtype=bool)
    unmatched = near_candidates(candidates.points[recheck], other, other_unmatched)
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
    return gap


def _level_below_share(
    candidates: Candidates,
    labels: NDArray[np.int64],
    recheck: NDArray[np.bool_],
    *,
    other: Side,
    min_radius: float = 0.0,
) -> NDArray[np.float64]:
    """Per part marked in ``recheck`` (0 elsewhere), the share of its candidates with a level
    surface of the other epoch straight under them within
    :data:`~app.core.localise.map_sides.SEE_THROUGH_REACH`, the probes at least ``min_radius``
    wide (:func:`~app.core.localise.map_planes.level_surface_below`)."""
    radius = max(min_radius, _probe_radius(other))
    return _probed_share(
        labels,
        recheck,
        lambda chosen: level_surface_below(
            candidates.points[chosen], other.geometry, SEE_THROUGH_REACH, radius
        ),
    )


def _gap_share(
    candidates: Candidates,
    labels: NDArray[np.int64],
    recheck: NDArray[np.bool_],
    *,
    own: Side,
    other: Side,
    tolerance: float,
) -> NDArray[np.float64]:
    """Per part marked in ``recheck`` (0 elsewhere), the share of its candidates in gaps
    between the other epoch's samples of a plane
    (:func:`~app.core.localise.map_planes.in_sampling_gap`), for a line of samples between its
    lines (:func:`~app.core.localise.map_lines.line_gap_share`), for a level part inside
    the other epoch's rim on its plane (:func:`~app.core.localise.map_rims.rim_gap_share`), or
    inside the other epoch's outline of its face
    (:func:`~app.core.localise.map_outlines.outline_gap_share`)."""
    share = _probed_share(
        labels,
        recheck,
        lambda chosen: part_sampling_gap(candidates, chosen, labels, other.geometry, tolerance),
    )
    for probe in (line_gap_share, rim_gap_share, outline_gap_share):
        share = np.maximum(
            share,
            probe(
                candidates.points,
                candidates.normal,
                labels,
                recheck & (share < GAP_SHARE),
                own=own.geometry,
                other=other.geometry,
                tolerance=tolerance,
            ),
        )
    return share


def _on_lacking_share(
    candidates: Candidates,
    labels: NDArray[np.int64],
    recheck: NDArray[np.bool_],
    *,
    own: Side,
    other: Side,
    other_unmatched: NDArray[np.bool_],
) -> NDArray[np.float64]:
    """Per part marked in ``recheck`` (0 elsewhere), the share of its candidates whose first
    level surface of the other epoch straight under them, within
    :data:`~app.core.localise.map_sides.SEE_THROUGH_REACH`, has a point this epoch lacks
    (:func:`~app.core.localise.map_planes.first_level_surface_marked`).  This epoch's own upright
    points that are no candidates stop the probe (a wall under a patch of it)."""

    def on_lacking(chosen: NDArray[np.int64]) -> NDArray[np.float64]:
        upright = np.abs(own.geometry.normal[:, 2]) < NORMAL_AGREEMENT_COSINE
        upright[candidates.index] = False
        return first_level_surface_marked(
            candidates.points[chosen],
            other.geometry,
            SEE_THROUGH_REACH,
            _probe_radius(other),
            marked=other_unmatched,
            blocking=KDTree(own.points[upright]) if upright.any() else None,
        )

    return _probed_share(labels, recheck, on_lacking)


def map_test(
    candidates: Candidates,
    *,
    own: Side,
    other: Side,
    threshold: float,
    change_threshold: float,
    cluster_factor: float,
    resting_band: float | None = None,
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
    resting_band : float, optional
        Height over the other epoch's support under which an upright foot rests on it
        (:func:`~app.core.localise.map_supports.map_statuses`); default ``change_threshold``.

    Returns
    -------
    MapEvidence
    """
    count = candidates.index.shape[0]
    if count == 0:
        status = np.full(count, STATUS_SEEN_THROUGH, dtype=np.int8)
        counts = {"map_clusters": 0, "map_coverage_clusters": 0}
        return MapEvidence(status, status.copy(), np.ones(count, dtype=np.float32), counts, None)
    radius = cluster_factor * candidates.spacing
    labels = surface_parts(candidates.points, candidates.normal, radius, step=change_threshold)
    labels, hosts = fragment_hosts(labels, candidates.points, radius, candidates.spacing)
    other_unmatched = unmatched_points(own, other, threshold, change_threshold)
    figures = part_figures(
        candidates,
        labels,
        own=own,
        other=other,
        other_unmatched=other_unmatched,
        threshold=threshold,
        change_threshold=change_threshold,
        cluster_factor=cluster_factor,
    )

    def see_through(recheck: NDArray[np.bool_], share: NDArray[np.float64]) -> NDArray[np.float64]:
        chosen = np.flatnonzero(recheck[labels])
        if chosen.shape[0] == 0:
            return share
        gap = _narrow_gaps(
            candidates,
            chosen,
            own=own,
            other=other,
            other_unmatched=other_unmatched,
            tolerance=threshold,
        )
        upright, counted = figures.upright, other_unmatched & ~gap
        plain = figures.continuation_share >= PLAIN_CONTINUATION_SHARE  # a layer hid it
        layer = np.where(plain, LAYER_FACTOR * change_threshold, 0.0)
        behind = seen_through(
            candidates, chosen, labels, upright, other, counted, threshold, layer, own.geometry
        )
        return _share_per_part(labels[chosen], behind, share)

    open_beneath = partial(_level_below_share, candidates, labels, other=other)

    far_face = partial(
        far_faces,
        candidates,
        labels,
        own=own,
        other=other,
        counted=other_unmatched,
        threshold=threshold,
        change_threshold=change_threshold,
        cluster_factor=cluster_factor,
    )
    stands_on_lacking = partial(
        _on_lacking_share, candidates, labels, own=own, other=other, other_unmatched=other_unmatched
    )
    in_gap = partial(_gap_share, candidates, labels, own=own, other=other, tolerance=threshold)

    check = unseen_faces(figures) & figures.upright
    hollow = hollow_sides(
        candidates, labels, figures, check, own, other, other_unmatched, threshold, change_threshold
    )
    reach = EDGE_FACTOR * change_threshold
    strips = strip_sides(figures, candidates.points, labels, other, other_unmatched, reach)
    coverage, faces, confidence, counts = part_verdict(
        figures, see_through, open_beneath, far_face, stands_on_lacking, in_gap, hollow, strips
    )
    coverage, confidence, counts["map_held_top_parts"] = with_held_tops(
        candidates, labels, figures, coverage, confidence, other, other_unmatched, change_threshold
    )
    seen = seen_round(figures, candidates, labels, other, change_threshold)
    verdict, clouds = (coverage, confidence, seen), (own.points, other.geometry)
    coverage, confidence, counts["map_blind_area_parts"] = settled_coverage(
        candidates, labels, radius, verdict, hosts, clouds, change_threshold, faces
    )
    status, evidence, counts["map_resting_points"] = map_statuses(
        candidates, labels, coverage[labels], other, threshold, resting_band or change_threshold
    )
    border = _face_border(candidates, labels, faces, figures.adjoined)
    return MapEvidence(status, evidence, confidence[labels].astype(np.float32), counts, border)


def _face_border(
    candidates: Candidates,
    labels: NDArray[np.int64],
    faces: NDArray[np.bool_],
    adjoined: NDArray[np.int64],
) -> FaceBorder:
    """The candidates of the ``faces`` parts (shape (parts,), bool) and those of them among the
    ``adjoined`` border points (indices into the candidates), as point indices."""
    members = np.flatnonzero(faces[labels])
    border = adjoined[faces[labels[adjoined]]]
    return FaceBorder(
        members=candidates.index[members],
        member_part=labels[members],
        border=candidates.index[border],
        border_part=labels[border],
    )


class MapTest:
    """The map test as a visibility test (``name = "maps"``)."""

    name = "maps"

    def __call__(
        self, candidates: Candidates, *, own: Side, other: Side, context: VisibilityContext
    ) -> VisibilityOutcome:
        """:func:`map_test` of ``own``'s candidates, on the :func:`metric_side` planes."""
        shared = context.shared or {}
        (metric_own, own_normal), (metric_other, _) = (
            metric_side(side, shared[side.name] if side.name in shared else metric_planes(side))
            for side in (own, other)
        )
        found = map_test(
            metric_candidates(candidates, own_normal),
            own=metric_own,
            other=metric_other,
            threshold=context.threshold,
            change_threshold=context.change_threshold,
            cluster_factor=context.settings["cluster_factor"],
            # a foot rests on a support within the noise-only threshold (crossing_candidates)
            resting_band=min(
                context.change_threshold,
                max(
                    context.settings["min_change_distance"],
                    context.settings["threshold_factor"]
                    * np.hypot(own.geometry.noise, other.geometry.noise),
                ),
            ),
        )
        return VisibilityOutcome(
            status=found.status,
            confidence=found.confidence,
            report=dict(found.counts),
            evidence=found.evidence,
            faces=found.faces,
        )
