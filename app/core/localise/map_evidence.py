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
  to continue or its border to meet the other epoch's faces (:func:`_verdict`).

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
from app.core.localise.map_parts import PartFigures, part_figures, surface_parts, unmatched_points
from app.core.localise.map_planes import (
    coplanar_sectors,
    first_level_surface_marked,
    in_sampling_gap,
    level_surface_below,
)
from app.core.localise.map_rims import rim_gap_share
from app.core.localise.map_scale import metric_candidates, metric_planes, metric_side
from app.core.localise.map_shared import (
    LAYER_FACTOR,
    LEVEL_BELOW_RADIUS,
    MIN_ADJOINING,
    seen_through,
    strip_sides,
    unseen_faces,
    unseen_levels,
)
from app.core.localise.map_sides import SEE_THROUGH_REACH, SPARSE_PROBE_FACTOR, near_candidates
from app.core.localise.map_supports import map_statuses
from app.core.localise.map_tops import with_held_tops
from app.core.localise.origin_free import BEHIND_MIN_RADIUS
from app.core.localise.rays import STATUS_SEEN_THROUGH, Candidates

__all__ = ["MapEvidence", "MapTest", "map_test", "unseen_faces"]


PLAIN_CONTINUATION_SHARE = 0.6
"""A cluster is a coverage difference when this share of its border points continues into a
surface the other epoch has (and no see-through evidence overrides it).  A removed object's
border continues into nothing parallel (its faces meet the floor and walls at an angle)."""
CONTINUATION_SHARE = 0.3
"""A patch of a wall or ceiling also meets the room's corners, so half its border may not
continue: from this share on, it is a coverage difference when most of its points also lie on
planes the other epoch has nearby (:data:`COPLANAR_SHARE`)."""
COPLANAR_SHARE = 0.75
GAP_SHARE = 0.5
"""A part is a coverage difference when this share of its points lies in gaps between the
other epoch's samples of one plane
(:func:`~app.core.localise.map_planes.in_sampling_gap`: single scan lines far from both paths,
each epoch's on its own place of the floor or a box top)."""
NARROW_SURROUND_SHARE = 0.35
"""An upright part whose adjoining border points have the other epoch's surface carrying on
past them in less than this share is a side of an object when the surface behind it is that
object's far face (:func:`~app.core.localise.map_faces.far_faces`): a narrow object's far face
lies within the surround probes, and the floor beyond it carries on past part of its border."""
SEE_THROUGH_SHARE = 0.6
"""A coverage-difference cluster is still a change when this share of its points has the
other epoch's surface, missing from this epoch, on its normal line within
:data:`SEE_THROUGH_REACH`, and so is an unseen side."""
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
    lines (:func:`~app.core.localise.map_lines.line_gap_share`), or for a level part inside
    the other epoch's rim on its plane (:func:`~app.core.localise.map_rims.rim_gap_share`)."""
    share = _probed_share(
        labels,
        recheck,
        lambda chosen: in_sampling_gap(
            candidates.points[chosen], candidates.normal[chosen], other.geometry, tolerance
        ),
    )
    for probe in (line_gap_share, rim_gap_share):
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
    coverage, faces, confidence, counts = _verdict(
        figures, see_through, open_beneath, far_face, stands_on_lacking, in_gap, hollow, strips
    )
    coverage, confidence, counts["map_held_top_parts"] = with_held_tops(
        candidates, labels, figures, coverage, confidence, other, other_unmatched, change_threshold
    )
    seen = seen_round(figures, candidates, labels, other, change_threshold)
    verdict = (coverage, confidence, seen)
    coverage, confidence, counts["map_blind_area_parts"] = settled_coverage(
        candidates, labels, radius, verdict, hosts, own.points, change_threshold, faces
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


def _continuing(
    part: PartFigures, in_gap: Any, unseen_side: NDArray[np.bool_]
) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
    """Per part, whether it lies on a surface that continues in the other epoch, and the
    share of its points in gaps between the other epoch's samples of one plane.

    Its border continues into the other epoch's surface (:data:`PLAIN_CONTINUATION_SHARE`, or
    :data:`CONTINUATION_SHARE` with :data:`COPLANAR_SHARE` of its points on the other epoch's
    planes), or :data:`GAP_SHARE` of its points lie between the other epoch's samples of a
    plane (``in_gap(recheck)``, for the near parts not continuing otherwise: a single scan
    line has no normal to continue along).  An ``unseen_side`` is read as that: the other
    epoch's surfaces meet it at an edge and end there, and the two epochs' map tests must
    still be able to agree on it (:mod:`~app.core.localise.map_agreement`: RGB-D room 203's
    old backrest, on a plane of the turned chair's points, 100 % -> 84 % without this)."""
    continues_plainly = part.continuation_share >= PLAIN_CONTINUATION_SHARE
    continues_in_plane = (part.continuation_share >= CONTINUATION_SHARE) & (
        part.coplanar_share >= COPLANAR_SHARE
    )
    continuing = continues_plainly | continues_in_plane
    gap_share = in_gap(part.near & ~continuing & ~unseen_side)
    return continuing | (gap_share >= GAP_SHARE), gap_share


def _verdict(
    figures: PartFigures,
    see_through: Any,
    open_beneath: Any,
    far_face: Any,
    on_lacking: Any,
    in_gap: Any,
    hollow: NDArray[np.bool_] | None = None,
    strips: NDArray[np.bool_] | None = None,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_], NDArray[np.float64], dict[str, Any]]:
    """Per part, whether it is a coverage difference, whether it is one as an unseen face
    only (:class:`~app.core.localise.interface.FaceBorder`), and the confidence in its
    verdict.

    ``see_through(recheck, behind_share)`` recomputes the see-through share of the parts
    marked in ``recheck`` without the other epoch's surface in narrow gaps of this one's
    (:func:`_narrow_gaps`).  It only lowers a share, so only parts at or over
    :data:`SEE_THROUGH_SHARE` are rechecked.  ``open_beneath(recheck)`` gives the share of
    the marked parts' points with a level surface of the other epoch straight under them
    (:func:`~app.core.localise.map_shared.unseen_faces`: an unseen top has its object's body
    under it).
    ``far_face(check)`` gives, per part, whether the surface behind it is its object's far
    face and the joined share (:func:`~app.core.localise.map_faces.far_faces`), for the parts
    marked in ``check``.  ``on_lacking(check)`` gives the share of the marked parts' points
    whose first level surface of the other epoch straight under them is surface this epoch
    lacks (:data:`SEE_THROUGH_SHARE` of an upright part's points: it stands on what it hides).
    ``in_gap`` is :func:`_continuing`'s.  ``hollow`` (shape (parts,), bool) marks the upright
    unseen sides that would bound a body holding points of the two epochs
    (:func:`~app.core.localise.map_bodies.hollow_sides`):
    they are no sides.  ``strips`` (shape (parts,), bool) marks the strips of a face both
    epochs saw along its edge (:func:`~app.core.localise.map_shared.edge_strips`, less the
    faces turned in place): unseen sides too.
    """
    part = figures
    unseen_side = unseen_faces(part) if strips is None else unseen_faces(part) | strips
    beneath = open_beneath(unseen_side & ~part.upright)
    unseen_side &= part.upright | (beneath < SEE_THROUGH_SHARE)
    hollow_side = (
        np.zeros_like(unseen_side) if hollow is None else hollow & unseen_side & part.upright
    )
    unseen_side &= ~hollow_side
    continuing, gap_share = _continuing(part, in_gap, unseen_side | hollow_side)
    # an upright part standing on a level surface that the other epoch saw and this one lacks
    # hides it: the other epoch saw its place empty (the seat under a backrest turned onto it,
    # seen from above its lower band only, in line with another chair's side)
    stands_on_hidden = part.upright & (
        on_lacking(part.upright & (continuing | unseen_side)) >= SEE_THROUGH_SHARE
    )
    continuing &= ~stands_on_hidden
    unseen_side &= ~stands_on_hidden
    see_through_share = see_through(
        continuing & (part.behind_share >= SEE_THROUGH_SHARE), part.behind_share
    )
    coverage = continuing & (see_through_share < SEE_THROUGH_SHARE)
    continues = coverage.copy()
    # an unseen side is overridden by the other epoch's surface behind it (a wall it hid),
    # unless that surface is the far face of the same object, seen from its far side only
    # (map_faces: the object's top and sides join the two faces in the other epoch).  With a
    # far face, a narrow object's side is one too: the other epoch's floor beyond its far face
    # lies within the surround probes, carrying on past part of its border
    narrow_side = (
        part.upright
        & (part.adjoining >= MIN_ADJOINING)
        & (part.surround_share < NARROW_SURROUND_SHARE)
    )
    far, joined_share = far_face(narrow_side & (part.behind_share >= SEE_THROUGH_SHARE))
    faces = (unseen_side & (part.behind_share < SEE_THROUGH_SHARE)) | far
    # a level patch with nothing of the other epoch's under or over it, on its planes nearby
    unseen_level = unseen_levels(part) & ~coverage
    unseen_level &= open_beneath(unseen_level, min_radius=LEVEL_BELOW_RADIUS) < SEE_THROUGH_SHARE
    coverage |= ~part.near | faces | unseen_level
    side_confidence = np.where(unseen_side, 1.0 - part.surround_share, 0.0)
    side_confidence = np.where(far, np.maximum(side_confidence, joined_share), side_confidence)
    side_confidence = np.where(unseen_level, part.coplanar_share, side_confidence)
    confidence = np.where(
        coverage,
        np.where(
            part.near,
            np.maximum(np.maximum(part.continuation_share, gap_share), side_confidence),
            1.0,
        ),
        np.clip(1.0 - part.continuation_share, 0.0, 1.0)
        * np.clip(0.5 + part.behind_share / (2 * SEE_THROUGH_SHARE), 0.0, 1.0),
    )
    counts = {
        "map_clusters": int(part.sizes.shape[0]),
        "map_coverage_clusters": int(coverage.sum()),
        "map_far_clusters": int((~part.near).sum()),
        **part.counts,
        "map_unseen_side_clusters": int((unseen_side & coverage).sum()),
        "map_far_face_parts": int(far.sum()),
        "map_standing_on_hidden_parts": int(stands_on_hidden.sum()),
        "map_hollow_side_parts": int(hollow_side.sum()),
        "map_edge_strip_parts": int(0 if strips is None else strips.sum()),
        "map_sampling_gap_parts": int((gap_share >= GAP_SHARE).sum()),
        "map_unseen_level_parts": int(unseen_level.sum()),
        "map_coplanar_share_median": float(np.median(part.coplanar_share)),
    }
    return coverage, faces & part.near & ~continues, confidence, counts


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
            # a foot rests on a support within the noise-only threshold (distance.crossing_...)
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
