"""The map test's verdict per surface part: coverage difference, unseen face or change.

:func:`part_verdict` weighs one fused map's surface parts (:class:`~app.core.localise.map_parts.
PartFigures`) with the probes :func:`~app.core.localise.map_evidence.map_test` hands it: does a
part lie on a surface that continues in the other epoch (:func:`continuing_parts`), did the
other epoch see through it, is it an unseen face of an object both epochs have, does it stand
on what it hides.  The shares that decide are this module's constants.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.core.localise.map_parts import PartFigures
from app.core.localise.map_shared import (
    LEVEL_BELOW_RADIUS,
    MIN_ADJOINING,
    unseen_faces,
    unseen_levels,
)

__all__ = [
    "CONTINUATION_SHARE",
    "COPLANAR_SHARE",
    "GAP_SHARE",
    "NARROW_SURROUND_SHARE",
    "PLAIN_CONTINUATION_SHARE",
    "SEE_THROUGH_SHARE",
    "continuing_parts",
    "part_verdict",
]

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


def continuing_parts(
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


def part_verdict(
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
    (:func:`~app.core.localise.map_evidence._narrow_gaps`).  It only lowers a share, so only
    parts at or over :data:`SEE_THROUGH_SHARE` are rechecked.  ``open_beneath(recheck)`` gives
    the share of the marked parts' points with a level surface of the other epoch straight under
    them (:func:`~app.core.localise.map_shared.unseen_faces`: an unseen top has its object's body
    under it).
    ``far_face(check)`` gives, per part, whether the surface behind it is its object's far
    face and the joined share (:func:`~app.core.localise.map_faces.far_faces`), for the parts
    marked in ``check``.  ``on_lacking(check)`` gives the share of the marked parts' points
    whose first level surface of the other epoch straight under them is surface this epoch
    lacks (:data:`SEE_THROUGH_SHARE` of an upright part's points: it stands on what it hides).
    ``in_gap`` is :func:`continuing_parts`'s.  ``hollow`` (shape (parts,), bool) marks the upright
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
    continuing, gap_share = continuing_parts(part, in_gap, unseen_side | hollow_side)
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
