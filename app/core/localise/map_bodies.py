"""The map test's unseen sides bound solid bodies: a side stands only if its body hides its inside.

The map test calls an upright part an unseen side
(:func:`~app.core.localise.map_shared.unseen_faces`) when the other epoch's surfaces meet its
border at an edge and end there: the other faces of an object standing in both epochs, of which
only this epoch's path faced this one.  Two faces of one solid object meet at its corner and
close its inside: from the part's plane, the object's body runs towards the side on which the
other epoch's meeting faces lie, as deep as they run, along the part's whole width and up to
its top.  Nothing inside a solid body can be seen, so neither epoch has a point there.

A chair turned a quarter in place leaves the old backrest and the new one meeting at the corner
they share, each ending at the other, exactly as two sides of a box each path saw one of meet.
But the box those two sides would bound holds the chair's seat, which both epochs saw from
above: the two backrests close no body, and each is a change of its epoch.

:func:`hollow_sides` measures this in each cloud's own terms: the body's depth from the other
epoch's meeting surfaces, margins of ``tau`` or one local spacing inside each bounding plane,
and the points of both epochs inside it.  It looks only at sides whose meeting surfaces are
in good part surface this epoch lacks (two faces, one per epoch, meeting at a corner): where
this epoch has them too, the side belongs to an object both epochs saw, whatever its shape (an
unchanged chair's legs and seat edge, open under its seat).  No sensor position, no ring
pattern.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from app.core.localise.distance import Side
from app.core.localise.gaps import NORMAL_AGREEMENT_COSINE, PLANE_SLOPE
from app.core.localise.map_faces import EDGE_FACTOR, meeting_planes
from app.core.localise.map_parts import UPRIGHT_NORMAL_Z, PartFigures
from app.core.localise.map_surround import SURROUND_REACH
from app.core.localise.rays import Candidates
from app.core.localise.settings import GATHER_CHUNK

__all__ = ["body_inside_counts", "hollow_sides"]

INSIDE_POINTS = 3
LACKING_SHARE = 0.25
"""The body test is for sides whose meeting surfaces are, for at least this share of their
points near the part, surface this epoch lacks: two faces, one per epoch, meeting at a corner
(a box each path saw one side of, or an object turned in place).  Where this epoch has the
meeting surfaces too, the part is an unseen side of an object both epochs saw, whatever its
shape (the legs and seat edge of a chair, open under its seat)."""
"""A body with at least this many points of the two epochs inside it is hollow: no body."""
DEPTH_QUANTILE = 0.9
"""The body runs as deep as this quantile of the meeting surfaces' points (robust to a stray
point of a surface beyond)."""
MARGIN_SPACINGS = 1.0
"""The inside starts this many local spacings (at least ``tau``) in from each bounding plane:
the faces' own samples, spread by noise, lie outside it."""
MEETING_POINTS = 256
"""The other epoch's points looked at around a meeting border point (within the reach)."""


def _part_frames(
    candidates: Candidates, labels: NDArray[np.int64], parts: NDArray[np.int64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per part in ``parts`` (shape (p,)), its horizontal unit normal (shape (p, 3), z = 0)
    and its plane's offset along it (shape (p,)); a zero normal where it has none."""
    normals = np.zeros((parts.shape[0], 3))
    offsets = np.zeros(parts.shape[0])
    for row, part in enumerate(parts):
        members = np.flatnonzero(labels == part)
        flat = candidates.points[members, :2]
        if members.shape[0] < 3:
            continue
        _, vectors = np.linalg.eigh(np.cov(flat.T))
        normals[row, :2] = vectors[:, 0]
        offsets[row] = float(np.median(candidates.points[members] @ normals[row]))
    return normals, offsets


def _meeting_offsets(
    points: NDArray[np.float64],
    toward: NDArray[np.floating],
    other: Side,
    *,
    tolerance: float,
    change_threshold: float,
) -> tuple[NDArray[np.bool_], NDArray[np.int64]]:
    """The other epoch's upright surface meeting each border point at an edge, as its points
    near it (shapes (b, 3), (b, 3) -> (b,), (b, k)): whether one meets the point, and the
    indices of its points within :data:`~app.core.localise.map_surround.SURROUND_REACH` on its
    plane (-1 elsewhere)."""
    count = points.shape[0]
    k = min(MEETING_POINTS, other.points.shape[0])
    meets = np.zeros(count, dtype=bool)
    found_index = np.full((count, k), -1, dtype=np.int64)
    reach = EDGE_FACTOR * change_threshold
    unit = toward.astype(np.float64)
    unit /= np.maximum(np.linalg.norm(unit, axis=1), 1e-12)[:, None]
    for start in range(0, count, GATHER_CHUNK):
        chunk = slice(start, start + GATHER_CHUNK)
        query = points[chunk]
        found, centroid, plane_normal = meeting_planes(query, unit[chunk], other, 2.0 * reach)
        height = np.einsum("cd,cd->c", query - centroid, plane_normal)
        upright = np.abs(plane_normal[:, 2]) < UPRIGHT_NORMAL_Z
        meets[chunk] = found & (np.abs(height) <= reach) & upright
        distance, index = other.geometry.tree.query(query, k=k, distance_upper_bound=SURROUND_REACH)
        distance = np.asarray(distance).reshape(query.shape[0], k)
        index = np.minimum(
            np.asarray(index, dtype=np.int64).reshape(query.shape[0], k),
            other.points.shape[0] - 1,
        )
        offset = other.points[index] - centroid[:, None, :]
        across = np.abs(np.einsum("ckd,cd->ck", offset, plane_normal))
        along = np.linalg.norm(offset, axis=2)
        agrees = np.abs(
            np.einsum("ckd,cd->ck", other.geometry.normal[index].astype(np.float64), plane_normal)
        )
        on_plane = (
            (distance <= SURROUND_REACH)
            & (across <= tolerance + PLANE_SLOPE * along)
            & (agrees >= NORMAL_AGREEMENT_COSINE)
            & meets[chunk][:, None]
        )
        found_index[chunk] = np.where(on_plane, index, -1)
    return meets, found_index


def _inside(
    cloud: NDArray[np.float64],
    corner: NDArray[np.float64],
    axes: NDArray[np.float64],
    extent: NDArray[np.float64],
) -> int:
    """How many of ``cloud``'s points (shape (n, 3)) lie in the box from ``corner`` spanned by
    the unit ``axes`` (shape (3, 3), rows) over ``extent`` (shape (3,), each > 0)."""
    far = corner + (axes * extent[:, None]).sum(axis=0)
    spans = np.vstack([corner, far, corner + axes[0] * extent[0], corner + axes[1] * extent[1]])
    low, high = spans.min(axis=0), spans.max(axis=0)
    low[2], high[2] = corner[2], corner[2] + extent[2]
    near = np.all((cloud >= low) & (cloud <= high), axis=1)
    local = (cloud[near] - corner) @ axes.T
    return int(np.count_nonzero(np.all((local > 0.0) & (local < extent), axis=1)))


def body_inside_counts(
    candidates: Candidates,
    labels: NDArray[np.int64],
    check: NDArray[np.bool_],
    adjoined: NDArray[np.int64],
    *,
    own: Side,
    other: Side,
    lacking: NDArray[np.bool_],
    tolerance: float,
    change_threshold: float,
) -> NDArray[np.int64]:
    """Per part marked in ``check`` (shape (parts,)), how many points of the two epochs lie
    inside the solid body it would bound as a side (-1 where none is looked at: no upright
    meeting surface on one side of it, meeting surfaces this epoch has too (less than
    :data:`LACKING_SHARE` of their points in ``lacking``, shape (m,)), or a body thinner than
    its margins).

    The body runs from the part's plane towards the side where the other epoch's upright
    surfaces meeting its ``adjoined`` border points (indices into the candidates) lie, as deep
    as they run (:data:`DEPTH_QUANTILE`, at most
    :data:`~app.core.localise.map_surround.SURROUND_REACH`), along the part's horizontal width,
    from one change threshold under its lowest point up to its top; :data:`MARGIN_SPACINGS`
    local spacings (at least ``tolerance``) in from each bounding plane.
    """
    counts = np.full(check.shape[0], -1, dtype=np.int64)
    parts = np.flatnonzero(check)
    border = adjoined[check[labels[adjoined]]]
    if parts.shape[0] == 0 or border.shape[0] == 0:
        return counts
    meets, index = _meeting_offsets(
        candidates.points[border],
        candidates.normal[border],
        other,
        tolerance=tolerance,
        change_threshold=change_threshold,
    )
    normals, offsets = _part_frames(candidates, labels, parts)
    for row, part in enumerate(parts):
        mine = meets & (labels[border] == part)
        found = np.unique(index[mine][index[mine] >= 0])
        if found.shape[0] == 0 or not normals[row].any():
            continue
        if np.mean(lacking[found]) < LACKING_SHARE:
            continue
        depth = other.points[found] @ normals[row] - offsets[row]
        side = 1.0 if np.median(depth) > 0.0 else -1.0
        depth = side * depth
        if not np.any(depth > 0.0):
            continue
        depth = min(SURROUND_REACH, float(np.quantile(depth[depth > 0.0], DEPTH_QUANTILE)))
        members = np.flatnonzero(labels == part)
        spacing = float(np.median(candidates.spacing[members]))
        margin = max(tolerance, MARGIN_SPACINGS * spacing)
        inward = side * normals[row]
        width_axis = np.cross(np.array([0.0, 0.0, 1.0]), inward)
        across = candidates.points[members] @ width_axis
        heights = candidates.points[members, 2]
        extent = np.array(
            [
                float(across.max() - across.min()) - 2.0 * margin,
                depth - 2.0 * margin,
                float(heights.max() - heights.min()) + change_threshold - margin,
            ]
        )
        if np.any(extent <= 0.0):
            continue
        corner = (
            (float(across.min()) + margin) * width_axis
            + (side * offsets[row] + margin) * inward
            + np.array([0.0, 0.0, float(heights.min()) - change_threshold])
        )
        axes = np.vstack([width_axis, inward, [0.0, 0.0, 1.0]])
        counts[part] = _inside(own.points, corner, axes, extent) + _inside(
            other.points, corner, axes, extent
        )
    return counts


def hollow_sides(
    candidates: Candidates,
    labels: NDArray[np.int64],
    figures: PartFigures,
    check: NDArray[np.bool_],
    own: Side,
    other: Side,
    lacking: NDArray[np.bool_],
    tolerance: float,
    change_threshold: float,
) -> NDArray[np.bool_]:
    """Per part marked in ``check`` (shape (parts,), bool; ``figures``: the parts' figures),
    whether the body it would bound as an unseen side holds at least :data:`INSIDE_POINTS`
    points of the two epochs (:func:`body_inside_counts`, the other arguments as there): no
    solid object has such a side, so it is none."""
    counts = body_inside_counts(
        candidates,
        labels,
        check,
        figures.adjoined,
        own=own,
        other=other,
        lacking=lacking,
        tolerance=tolerance,
        change_threshold=change_threshold,
    )
    return counts >= INSIDE_POINTS
