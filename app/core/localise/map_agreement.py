"""The two epochs' map tests agree: an unseen face meets no change of the other epoch.

The map test calls a part an unseen face (:func:`~app.core.localise.map_shared.unseen_faces`)
when the other epoch's surfaces meet its border at an edge and end there: they are taken for
the other faces (top, other sides) of an object standing in both epochs, of which only this
epoch's path saw this face.  That holds only when those surfaces are the same object in the
other epoch's map.  Where the other epoch's surface meeting the part carries on into a change
of the other epoch (its own map test found that this epoch saw that place empty), the two
surfaces are not two faces of one standing object: they are the object before and after it
moved or turned.  A chair turned a quarter in place leaves the old backrest meeting the new
one at the corner they share, exactly as two faces of a box each path saw one of would meet;
the new backrest, past the change threshold from the old one, is a change of the other epoch.

Each side's map test runs on its own; :func:`faces_meeting_changes` then reads both sides' labels
once (the verdicts of the first pass, never the overturned ones: the result does not depend
on which side is read first) and makes the unseen faces that meet the other epoch's changes
changes (``seen_empty``).  Measured in each cloud's own spacing and the change threshold: no
sensor position, no ring pattern.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from app.core.labels import LABEL_CHANGED, LABEL_UNCHANGED
from app.core.localise.distance import Side
from app.core.localise.gaps import NORMAL_AGREEMENT_COSINE, PLANE_SLOPE
from app.core.localise.interface import FaceBorder
from app.core.localise.map_faces import EDGE_FACTOR, meeting_planes
from app.core.localise.map_surround import SURROUND_REACH
from app.core.localise.settings import GATHER_CHUNK

__all__ = ["changed_share", "faces_meeting_changes", "faces_of_changes"]

CHANGED_SURFACE_SHARE = 0.5
"""A border point meets a change of the other epoch when the other side called at least this
share of the surface meeting it changed, of the part of it this epoch lacks
(:func:`changed_share`)."""
MIN_JUDGED = 3
"""Fewer judged points of the meeting surface than this say nothing."""
MEETING_SHARE = 0.5
"""An unseen face is a change when at least this share of its border points that the other
epoch's surface meets at an edge meet a change of the other epoch."""
MIN_MEETING = 5
"""Fewer such border points than this say nothing."""
AGREEMENT_NEIGHBOURS = 256
"""The other epoch's points looked at around a border point (within the reach)."""


def changed_share(
    points: NDArray[np.float64],
    normal: NDArray[np.floating],
    other: Side,
    other_label: NDArray[np.int8],
    *,
    tolerance: float,
    change_threshold: float,
) -> NDArray[np.float64]:
    """How much of the other epoch's surface meeting each point, where this epoch lacks it, the
    other side called changed (shapes (b, 3), (b, 3) -> (b,)).

    The surface meeting a point at an edge is a plane fitted to the other cloud's points near
    it (within :data:`~app.core.localise.map_faces.EDGE_FACTOR` change thresholds), two ways:
    to the 16 nearest (:func:`~app.core.localise.map_faces.meeting_planes`) and to those of
    the 64 nearest whose normals most agree (``dominant``); the larger
    share counts.  The nearest fit finds a surface meeting a clean corner close by (clean
    RGB-D room 803's turned chair: 94 % with it, 80 % with the dominant fit alone), the
    dominant fit one meeting a corner the drift smeared (room 1403: 25 % -> 91 %).  Its
    points are the
    other cloud's points within :data:`~app.core.localise.map_surround.SURROUND_REACH` (at most
    :data:`AGREEMENT_NEIGHBOURS`) on that plane (within ``tolerance``, widening with the
    distance, normals agreeing).  Of those the other side judged (its change candidates:
    changed or unobserved, ``other_label``, shape (m,)), the share it called changed; 0 where
    it judged fewer than :data:`MIN_JUDGED`.
    """
    count = points.shape[0]
    share = np.zeros(count)
    if count == 0 or other.points.shape[0] == 0:
        return share
    unit = normal.astype(np.float64)
    unit /= np.maximum(np.linalg.norm(unit, axis=1), 1e-12)[:, None]
    reach = EDGE_FACTOR * change_threshold
    k = min(AGREEMENT_NEIGHBOURS, other.points.shape[0])
    for start in range(0, count, GATHER_CHUNK):
        chunk = slice(start, start + GATHER_CHUNK)
        query = points[chunk]
        distance, index = other.geometry.tree.query(query, k=k, distance_upper_bound=SURROUND_REACH)
        distance = np.asarray(distance).reshape(query.shape[0], k)
        index = np.minimum(np.asarray(index).reshape(query.shape[0], k), other.points.shape[0] - 1)
        for dominant in (False, True):
            plane = meeting_planes(query, unit[chunk], other, 2.0 * reach, dominant=dominant)
            share[chunk] = np.maximum(
                share[chunk],
                _share_on_plane(
                    query, plane, (distance, index), other, other_label, reach, tolerance
                ),
            )
    return share


def _share_on_plane(
    query: NDArray[np.float64],
    plane: tuple[NDArray[np.bool_], NDArray[np.float64], NDArray[np.float64]],
    near: tuple[NDArray[np.float64], NDArray[np.int64]],
    other: Side,
    other_label: NDArray[np.int8],
    reach: float,
    tolerance: float,
) -> NDArray[np.float64]:
    """The share of :func:`changed_share` for each of ``query`` (shape (b, 3) -> (b,)) on one
    fitted meeting ``plane`` (found (b,), centroid (b, 3), normal (b, 3)), given the other
    cloud's points ``near`` each (distances and indices, shapes (b, k))."""
    found, centroid, plane_normal = plane
    distance, index = near
    height = np.einsum("cd,cd->c", query - centroid, plane_normal)
    meets = found & (np.abs(height) <= reach)
    offset = other.points[index] - (query - height[:, None] * plane_normal)[:, None, :]
    along = np.linalg.norm(offset, axis=2)
    across = np.abs(np.einsum("ckd,cd->ck", offset, plane_normal))
    agrees = np.abs(
        np.einsum("ckd,cd->ck", other.geometry.normal[index].astype(np.float64), plane_normal)
    )
    judged = (
        (distance <= SURROUND_REACH)
        & (across <= tolerance + PLANE_SLOPE * along)
        & (agrees >= NORMAL_AGREEMENT_COSINE)
        & (other_label[index] != LABEL_UNCHANGED)
    )
    changed = (judged & (other_label[index] == LABEL_CHANGED)).sum(axis=1)
    enough = meets & (judged.sum(axis=1) >= MIN_JUDGED)
    return np.where(enough, changed / np.maximum(judged.sum(axis=1), 1), 0.0)


def border_normals(own: Side, faces: FaceBorder) -> NDArray[np.float64]:
    """The normal of each face border point's part: the least axis of the part's members'
    positions (shape (b, 3)); a part of fewer than 3 members keeps its points' own normals.

    A border point's own normal leans where its part meets another surface (its neighbours
    take in both): at the corner where an old backrest meets the turned one it leans towards
    the turned one, and the other epoch's surface at more than 60 degrees to it is then sought
    among the samples parallel to the part (the seat's side under it), not the turned
    backrest.  The part's own plane is the one the meeting surface stands at an edge to.
    """
    normal = own.geometry.normal[faces.border].astype(np.float64)
    for part in np.unique(faces.border_part):
        positions = own.points[faces.members[faces.member_part == part]]
        if positions.shape[0] >= 3:
            normal[faces.border_part == part] = np.linalg.eigh(np.cov(positions.T))[1][:, 0]
    return normal


def faces_of_changes(
    faces: FaceBorder,
    own: Side,
    other: Side,
    other_label: NDArray[np.int8],
    *,
    tolerance: float,
    change_threshold: float,
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """The unseen faces' members to make changes (point indices) and each one's share of
    border points meeting a change (its confidence)."""
    if faces.border.shape[0] == 0:
        return faces.members[:0], np.zeros(0)
    meets = (
        changed_share(
            own.points[faces.border],
            border_normals(own, faces),
            other,
            other_label,
            tolerance=tolerance,
            change_threshold=change_threshold,
        )
        >= CHANGED_SURFACE_SHARE
    )
    parts = int(max(faces.border_part.max(), faces.member_part.max())) + 1
    meeting = np.bincount(faces.border_part, minlength=parts).astype(np.float64)
    share = np.bincount(faces.border_part, weights=meets.astype(np.float64), minlength=parts)
    share /= np.maximum(meeting, 1.0)
    changed = (meeting >= MIN_MEETING) & (share >= MEETING_SHARE)
    chosen = changed[faces.member_part]
    return faces.members[chosen], share[faces.member_part[chosen]]


def faces_meeting_changes(
    sides: tuple[Side, Side],
    labels: tuple[NDArray[np.int8], NDArray[np.int8]],
    faces: tuple[FaceBorder | None, FaceBorder | None],
    *,
    tolerance: float,
    change_threshold: float,
) -> list[tuple[NDArray[np.int64], NDArray[np.float64]]]:
    """Per side, its unseen faces that meet a change of the other epoch (point indices) and
    the confidence of each (:func:`faces_of_changes`), read from both sides' first labels.

    Parameters
    ----------
    sides : (Side, Side)
        The reference's and the scan's side.
    labels : (ndarray, ndarray)
        Each cloud's labels from its own visibility test, shapes (n,) and (m,).
    faces : (FaceBorder or None, FaceBorder or None)
        Each cloud's unseen faces (None: its test was not the map test).
    tolerance, change_threshold : float
        ``tau`` and ``c`` (metres).

    Returns
    -------
    list of two (indices, confidence) pairs
        Indices of shape (f,) into the side's points, confidences of shape (f,).
    """
    found = []
    for own, other, own_faces, other_label in (
        (sides[0], sides[1], faces[0], labels[1]),
        (sides[1], sides[0], faces[1], labels[0]),
    ):
        if own_faces is None:
            found.append((np.zeros(0, dtype=np.int64), np.zeros(0)))
            continue
        found.append(
            faces_of_changes(
                own_faces,
                own,
                other,
                other_label,
                tolerance=tolerance,
                change_threshold=change_threshold,
            )
        )
    return found
