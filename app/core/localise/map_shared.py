"""Faces of objects standing in both epochs that only one epoch saw (:func:`unseen_faces`), and
level patches of a surface the other epoch saw elsewhere only (:func:`unseen_levels`).

A sparse map sees an upright face in lidar columns, each epoch's elsewhere.  A column next to
the face's edge lies between the other epoch's columns on the face and the edge, where the
other epoch's side round the corner ends (:func:`edge_strips`: robot warehouse 804's rack end).
A face turned in place looks the same to the figures (a chair's new backrest seen from afar, on
the plane of the seat's side, the other epoch's seat top ending at it: robot warehouse 604),
but it meets the old face, surface this epoch lacks, at an angle next to it
(:func:`meets_lacking_at_angle`); a strip of a face both epochs saw meets only surface both
have.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.localise.distance import Side
from app.core.localise.gaps import NORMAL_AGREEMENT_COSINE
from app.core.localise.map_parts import UPRIGHT_NORMAL_Z, PartFigures
from app.core.localise.map_planes import extends
from app.core.localise.map_sides import oriented_depths, surface_behind
from app.core.localise.map_surround import EDGE_COSINE
from app.core.localise.rays import Candidates
from app.core.localise.surface import LocalGeometry

__all__ = [
    "LAYER_FACTOR",
    "LEVEL_BELOW_RADIUS",
    "MIN_ADJOINING",
    "SURROUND_SHARE",
    "edge_strips",
    "layered_behind",
    "meets_lacking_at_angle",
    "seen_through",
    "standing_layer",
    "strip_sides",
    "unseen_faces",
    "unseen_levels",
]

LAYER_FACTOR = 2.0
"""The other epoch's lacking surface within this many change thresholds of a part whose
surface it has all round is a layer on that surface (an object standing against it), no
surface seen through the part's place (:func:`layered_behind`)."""
LAYER_NEIGHBOURS = 16
"""The other cloud's points looked at round a point for an object standing in its layer."""
SURROUND_SHARE = 0.1
"""An upright part is an unseen side when less than this share of its adjoining border points
has the other epoch's surface carrying on past them (or surface this epoch lacks)."""
MIN_ADJOINING = 5
"""Fewer adjoining border points than this say nothing about a part."""
STRIP_COPLANAR_SHARE = 0.75
"""An edge strip lies on planes the other epoch has nearby with this share of its points."""
MIN_MEETING = 3
"""A part meets the other epoch's lacking surface when this many of its points lie next to it."""
MEETING_NEIGHBOURS = 8
"""The other epoch's lacking points looked at around each of the part's points."""
LEVEL_BEHIND_SHARE = 0.1
"""A level part with the other epoch's surface (that this epoch lacks) on the normal lines of
fewer than this share of its points has nothing under or over it that the other epoch saw."""
LEVEL_COPLANAR_SHARE = 0.5
"""... and with at least this share of its points on planes the other epoch has nearby, it is a
patch of a surface the other epoch saw elsewhere (:func:`unseen_levels`)."""
LEVEL_BELOW_RADIUS = 0.15
"""Metres: the probes for a level surface under a level part (:func:`unseen_levels`) are balls at
least this wide.  A sparse robot map samples the floor in ring arcs 0.1-0.4 m apart: narrower
probes under an added chair's seat 0.45 m over it fell between the arcs (held-out robot office
2302: the seat taken for a patch the other epoch saw elsewhere, the chair 59 % found; 0.25 m
also took 92 more points of the real pairs outside their annotated changes).  A ceiling patch
3 m over the floor still has none within reach."""
LEVEL_MIN_POINTS = 8
"""A part of fewer points has no share to speak of (a 2-point level strip of a chair added at
the real classroom's front wall, 1 of its 2 points on a plane of the other epoch's)."""


def unseen_faces(figures: PartFigures) -> NDArray[np.bool_]:
    """Per part, whether it is a face of an object standing in both epochs that only this
    epoch's path saw (shape (parts,), bool).

    The other epoch's surfaces adjoin the part at an edge and end at it, instead of carrying
    on past it (:data:`MIN_ADJOINING` border points, fewer than :data:`SURROUND_SHARE` carried
    on): the other epoch saw the object's other faces, not this one.  An upright side has the
    object's top and its other sides ending at its edges; a top (a box on a desk, a cabinet
    the other path never looked down on) has the object's sides ending at its rim.  The other
    epoch's surfaces carry on past a removed or added object's faces (the floor, desk top or
    wall it stood on or against), or are surface this epoch lacks; a supporting surface ending
    at a part is no evidence either way (:func:`~app.core.localise.map_surround._supports`).
    Tops were left out before (s10): on six seeds of RGB-D rooms, horizontal parts meeting
    this rule carry 1,800 false changed points on unseen tops and desk strips and 71 true ones.
    A top is one only when the other epoch has no level surface straight under most of it
    within :data:`~app.core.localise.map_sides.SEE_THROUGH_REACH`
    (:func:`~app.core.localise.map_verdict.part_verdict`,
    :func:`~app.core.localise.map_planes.level_surface_below`): a solid object's body hides
    everything under its top, while under a removed table the other epoch saw the floor (the
    real classroom's table).  Until s12 that probe looked up as well and reached 1.42 m: it
    found the ceiling over a box's top as often as what lay under it.
    """
    return (figures.adjoining >= MIN_ADJOINING) & (figures.surround_share < SURROUND_SHARE)


def edge_strips(figures: PartFigures) -> NDArray[np.bool_]:
    """Per part, whether it may be a strip of a face both epochs saw, along the face's edge
    (shape (parts,), bool): upright, on planes the other epoch has nearby
    (:data:`STRIP_COPLANAR_SHARE` of its points), with fewer than :data:`MIN_ADJOINING` (but
    some) border points that the other epoch's surface meets at an edge, that surface ending
    at them (under :data:`SURROUND_SHARE` carried on past).

    A column next to the face's edge is a few samples wide: too few border points meet the
    other epoch's side round the corner for :func:`unseen_faces`, and its half-plane towards
    the edge is empty (:func:`~app.core.localise.map_planes.in_sampling_gap`).  A face turned in
    place has the same figures: :func:`meets_lacking_at_angle` tells them apart."""
    return (
        figures.upright
        & (figures.adjoining >= 1)
        & (figures.adjoining < MIN_ADJOINING)
        & (figures.surround_share < SURROUND_SHARE)
        & (figures.coplanar_share >= STRIP_COPLANAR_SHARE)
    )


def meets_lacking_at_angle(
    points: NDArray[np.float64],
    labels: NDArray[np.int64],
    check: NDArray[np.bool_],
    other: Side,
    other_unmatched: NDArray[np.bool_],
    reach: float,
) -> NDArray[np.bool_]:
    """Per part marked in ``check`` (shape (parts,); False elsewhere), whether
    :data:`MIN_MEETING` of its candidates (``points`` shape (c, 3), ``labels`` shape (c,)) lie
    within ``reach`` of the other cloud's points that this epoch lacks (``other_unmatched``,
    shape (m,), bool) on an upright surface at an angle to the part's plane (normals' cosine
    under :data:`~app.core.localise.map_surround.EDGE_COSINE`).

    That surface is a change of the other epoch meeting the part at an edge: the face the part
    was turned from (a chair's old backrest at the corner it shares with the new one).  A strip
    of a face both epochs saw meets the object's other faces, which both epochs have."""
    met = np.zeros(check.shape[0], dtype=bool)
    normal = other.geometry.normal.astype(np.float64)
    lacking = np.flatnonzero(other_unmatched & (np.abs(normal[:, 2]) < UPRIGHT_NORMAL_Z))
    if lacking.shape[0] == 0:
        return met
    tree = KDTree(other.points[lacking])
    for part in np.flatnonzero(check):
        face = points[labels == part]
        if face.shape[0] < MIN_MEETING:
            continue
        _, vectors = np.linalg.eigh(np.cov((face - face.mean(axis=0)).T))
        k = min(MEETING_NEIGHBOURS, lacking.shape[0])
        distance, index = tree.query(face, k=k, distance_upper_bound=reach)
        distance = np.asarray(distance).reshape(face.shape[0], k)
        index = np.minimum(np.asarray(index).reshape(face.shape[0], k), lacking.shape[0] - 1)
        at_angle = np.abs(normal[lacking[index]] @ vectors[:, 0]) < EDGE_COSINE
        meeting = ((distance <= reach) & at_angle).any(axis=1)
        met[part] = np.count_nonzero(meeting) >= MIN_MEETING
    return met


def seen_through(
    candidates: Candidates,
    chosen: NDArray[np.int64],
    labels: NDArray[np.int64],
    upright: NDArray[np.bool_],
    other: Side,
    counted: NDArray[np.bool_],
    tolerance: float,
    layer: NDArray[np.float64] | None = None,
    own: LocalGeometry | None = None,
) -> NDArray[np.bool_]:
    """Whether the other cloud's ``counted`` points (shape (m,), bool) lie on the normal line
    of each ``chosen`` candidate (indices, shape (k,) -> (k,), bool;
    :func:`~app.core.localise.map_sides.surface_behind`); for the candidates of a level part
    (``labels`` shape (c,) into ``upright`` shape (parts,), bool), only those lower than the
    part's median height less ``tolerance``.

    A level part (a floor patch, a desk top) is seen from above; the other epoch saw through
    its place only onto what lies under it (the floor under a removed box's top).  Its surface
    over the part is no see-through: it stood between the part and the other epoch's views and
    hid the part from them (robot office 303: the reference's desk top over a floor patch only
    the scan's lidar saw, from the side, under the desk).  An upright part's sensors may stand
    on either side of it: every counted surface on its normal line is evidence (the wall
    behind a turned backrest: RGB-D room 1103), except, for the upright parts with a
    ``layer`` (shape (parts,), metres, 0: none), an object standing within it
    (:func:`layered_behind`; ``own``: the candidates' cloud, needed with ``layer``)."""
    points, normal, labels = candidates.points[chosen], candidates.normal[chosen], labels[chosen]
    found = np.zeros(points.shape[0], dtype=bool)
    sides = upright[labels]
    layered = sides & ((np.zeros(upright.shape[0]) if layer is None else layer)[labels] > 0.0)
    plain = sides & ~layered
    found[plain] = surface_behind(points[plain], normal[plain], other, counted)
    if layered.any():
        found[layered] = layered_behind(
            points[layered], normal[layered], other, counted, layer[labels[layered]], own, tolerance
        )
    height = other.points[:, 2]
    for part in np.unique(labels[~sides]):
        members = np.flatnonzero(labels == part)
        below = counted & (height < float(np.median(points[members, 2])) - tolerance)
        found[members] = surface_behind(points[members], normal[members], other, below)
    return found


def layered_behind(
    points: NDArray[np.float64],
    normal: NDArray[np.floating],
    other: Side,
    counted: NDArray[np.bool_],
    layer: NDArray[np.float64],
    own: LocalGeometry,
    tolerance: float,
) -> NDArray[np.bool_]:
    """Whether the other cloud's ``counted`` surface on each point's normal line is evidence
    that the other epoch saw through the point's place (shapes (c, 3) -> (c,)): as
    :func:`~app.core.localise.map_sides.surface_behind`, except where an object stands within
    ``layer`` (metres, shape (c,)) of it (:func:`standing_layer`) and no such surface lies
    farther than ``layer`` on a side
    (:func:`~app.core.localise.map_sides.oriented_depths`).

    Asked for a part whose surface the other epoch has round it (it carries on past the
    part's border): the other epoch saw that surface there from its open side.  Its lacking
    surface parallel to the part and within ``layer`` of it, on a plane this epoch does not
    carry on, is taken as an object standing against the surface, which hid the part's place
    from the other epoch (a chair's back 7-12 cm before a warehouse wall, robot 2804: the
    scan's wall where the reference's chair stood), not as surface seen through it.  The part
    is then unseen by the other epoch, not seen empty.  A surface whose plane this epoch has
    round it is no such object but the wall behind the part (a removed board 12.5 cm before
    a wall: the board is seen through); surface farther than ``layer`` on a side is evidence
    as before (the wall behind a turned backrest)."""
    unit = normal.astype(np.float64)
    unit /= np.maximum(np.linalg.norm(unit, axis=1), 1e-12)[:, None]
    found = surface_behind(points, normal, other, counted)
    standing = standing_layer(
        points[found], unit[found], other, counted, layer[found], own, tolerance
    )
    if standing.any():
        rows = np.flatnonzero(found)[standing]
        ahead, back = oriented_depths(points[rows], unit[rows], other, counted)
        beyond = (np.isfinite(ahead) & (ahead > layer[rows])) | (
            np.isfinite(back) & (back > layer[rows])
        )
        found[rows] = beyond
    return found


def standing_layer(
    points: NDArray[np.float64],
    unit: NDArray[np.float64],
    other: Side,
    counted: NDArray[np.bool_],
    layer: NDArray[np.float64],
    own: LocalGeometry,
    tolerance: float,
) -> NDArray[np.bool_]:
    """Whether an object of the other epoch stands within ``layer`` (metres, shape (c,)) of
    each point on its normal line (``unit``, shape (c, 3) -> (c,), bool): a ``counted`` point
    of the other cloud at most ``layer`` along the line and ``layer / LAYER_FACTOR`` off it,
    its surface parallel to the point's, and its plane one ``own`` (the point's cloud) does not
    carry on (:func:`~app.core.localise.map_planes.extends`: the wall behind a removed board is
    on the reference's wall plane; the removed chair's back before the scan's wall is not).
    Measured on the points themselves: a probe's ball reaches farther than its depth (a sparse
    corridor's box front 0.5 m out of the wall, ``layer`` 0.39 m, is no layer)."""
    standing = np.zeros(points.shape[0], dtype=bool)
    chosen = np.flatnonzero(counted)
    if points.shape[0] == 0 or chosen.shape[0] == 0:
        return standing
    k = min(LAYER_NEIGHBOURS, chosen.shape[0])
    reach = float(np.max(layer)) * np.hypot(1.0, 1.0 / LAYER_FACTOR)
    _, index = KDTree(other.points[chosen]).query(points, k=k, distance_upper_bound=reach)
    index = chosen[np.minimum(np.asarray(index).reshape(points.shape[0], k), chosen.shape[0] - 1)]
    offset = other.points[index] - points[:, None, :]
    along = np.einsum("ckd,cd->ck", offset, unit)
    off_line = np.linalg.norm(offset - along[:, :, None] * unit[:, None, :], axis=2)
    parallel = np.abs(np.einsum("ckd,cd->ck", other.geometry.normal[index], unit))
    within = (
        (np.abs(along) <= layer[:, None])
        & (off_line <= layer[:, None] / LAYER_FACTOR)
        & (parallel >= NORMAL_AGREEMENT_COSINE)
    )
    rows = np.flatnonzero(within.any(axis=1))
    if rows.shape[0] == 0:
        return standing
    first = index[rows, np.argmax(within[rows], axis=1)]
    carried = extends(other.points[first], other.geometry.normal[first], own, tolerance)
    standing[rows] = ~carried
    return standing


def strip_sides(
    figures: PartFigures,
    points: NDArray[np.float64],
    labels: NDArray[np.int64],
    other: Side,
    other_unmatched: NDArray[np.bool_],
    reach: float,
) -> NDArray[np.bool_]:
    """Per part, whether it is a strip of a face both epochs saw along its edge
    (:func:`edge_strips`) that meets no surface this epoch lacks at an angle within ``reach``
    (:func:`meets_lacking_at_angle`: a face turned in place); shape (parts,), bool."""
    strips = edge_strips(figures)
    return strips & ~meets_lacking_at_angle(points, labels, strips, other, other_unmatched, reach)


def unseen_levels(figures: PartFigures) -> NDArray[np.bool_]:
    """Per part, whether it is a level patch of a surface that the other epoch saw elsewhere
    only (shape (parts,), bool): a coverage difference.

    The other epoch saw a level part's place empty only by seeing past it: the floor or desk
    top under a removed or added object's top, the floor under a removed table (its surface
    on the part's normal lines, which this epoch lacks: ``behind_share``).  A level part with
    none of that on the normal lines of its points (:data:`LEVEL_BEHIND_SHARE`), lying on
    planes the other epoch has nearby (:data:`LEVEL_COPLANAR_SHARE`; of
    :data:`LEVEL_MIN_POINTS` or more), is a patch of that
    surface which the other epoch's path never saw: a 16-ring lidar sees an office's ceiling
    1.9 m up in ring arcs metres from its path, each epoch's elsewhere, and the floor 3 m
    under it is out of reach (robot office 903, unchanged: 2 regions / 48 points of ceiling
    arcs in a corner, the other epoch's arcs nearer the corner only; the s17 line rule takes
    single arcs, not two side by side).  An added or removed object's top has the floor
    or desk under it seen by the other epoch: that surface, unless this epoch lacks it, says
    nothing on the normal lines, so the caller also requires that the other epoch has no
    level surface under most of the part within reach
    (:func:`~app.core.localise.map_planes.level_surface_below`; a removed chair's seat on a
    robot map, the floor under it seen by both epochs: robot office 902).
    """
    return (
        ~figures.upright
        & (figures.sizes >= LEVEL_MIN_POINTS)
        & (figures.behind_share < LEVEL_BEHIND_SHARE)
        & (figures.coplanar_share >= LEVEL_COPLANAR_SHARE)
    )
