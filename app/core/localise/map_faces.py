"""Which side of a face each epoch saw: far faces of objects that stand in both epochs.

A surface seen in a fused map was seen from one side, its open side.  The map test takes the
other epoch's surface on a candidate's normal line, surface this epoch lacks, as evidence that
the other epoch saw through the candidate's place (the floor under a removed chair, the wall
behind a removed board, the wall a box was pushed out of).  That holds only when the other
epoch saw that surface from the candidate's side.  An object standing in both epochs that each
path saw from its own side only has, behind each epoch's face, the other epoch's far face of
the same object, seen from the far side: back to back with the candidate, its open side facing
away.  The other epoch's view of it never crossed the candidate's place.

Which side of the far surface the other epoch saw is told by the surfaces that join it to the
candidate, the object's other faces: its top and its sides meet the candidate at an edge, run
from it towards the far surface and end there, in the other epoch.  They close the space
between the two faces into the object's inside, so both faces open outwards, away from each
other.  A wall or floor that the other epoch saw from the candidate's side is joined to it by
nothing, or by surfaces that carry on past one of the two (the ceiling over the paper's
corridor, whose wall moved 0.5 m, runs past both).  The test uses the geometry both epochs
share, measured in each cloud's own spacing: no sensor position, no ring pattern.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from app.core.localise.distance import Side
from app.core.localise.gaps import NORMAL_AGREEMENT_COSINE
from app.core.localise.map_sides import inner_sides, nearest_in_air, oriented_depths, part_axes
from app.core.localise.rays import Candidates
from app.core.localise.regions import CLUSTER_NEIGHBOURS
from app.core.localise.surface import weighted_plane

__all__ = ["FAR_FACE_SHARE", "far_faces", "meeting_planes"]

FAR_FACE_SHARE = 0.3
"""The surface behind a part is its object's far face when this share of the part's border
points that the other epoch's surfaces meet at an edge are joined to it (:func:`_joins`)."""
MIN_JOINING = 5
"""Fewer joining border points than this say nothing."""
EDGE_COSINE = math.cos(math.radians(60.0))
"""A surface meets a border point at an edge when the normals' cosine is below this."""
EDGE_FACTOR = 2.0
"""The other epoch's surface meets a border point within this many change thresholds."""
PROBE_SPACINGS = 1.5
"""A probe on a joining surface looks this many of the other cloud's spacings around it."""
PROBE_MIN_RADIUS = 0.05
PROBE_NEIGHBOURS = 4
MEETING_NEIGHBOURS = 16
"""The other epoch's points a meeting surface is fitted to."""
DOMINANT_NEIGHBOURS = 4 * MEETING_NEIGHBOURS
"""The other epoch's points among which a meeting surface's dominant samples are sought."""


def _on_plane(
    probes: NDArray[np.float64],
    plane_normal: NDArray[np.float64],
    radius: NDArray[np.float64],
    other: Side,
) -> NDArray[np.bool_]:
    """Whether the other cloud has a point within ``radius`` of each probe whose normal agrees
    with ``plane_normal`` (shapes (b, 3), (b,) -> (b,)): the probe lies on the plane, so such
    a point lies on it too, to within the radius."""
    k = min(PROBE_NEIGHBOURS, other.points.shape[0])
    distance, index = other.geometry.tree.query(
        probes, k=k, distance_upper_bound=float(radius.max())
    )
    distance = np.asarray(distance).reshape(probes.shape[0], k)
    index = np.minimum(np.asarray(index).reshape(probes.shape[0], k), other.points.shape[0] - 1)
    agrees = np.abs(np.einsum("bkd,bd->bk", other.geometry.normal[index], plane_normal))
    return ((distance <= radius[:, None]) & (agrees >= NORMAL_AGREEMENT_COSINE)).any(axis=1)


def meeting_planes(
    points: NDArray[np.float64],
    toward: NDArray[np.float64],
    other: Side,
    reach: float,
    *,
    dominant: bool = False,
) -> tuple[NDArray[np.bool_], NDArray[np.float64], NDArray[np.float64]]:
    """The plane of the other cloud's surface meeting each point at an edge: fitted to its
    :data:`MEETING_NEIGHBOURS` nearest points within ``reach`` whose normals are at more than
    60 degrees to ``toward`` (a fit to the points' positions: near a corner of a sparse cloud
    each point's own normal leans towards the other face).

    ``dominant``: fitted instead to those of its :data:`DOMINANT_NEIGHBOURS` nearest such points
    whose normals agree (:data:`~app.core.localise.gaps.NORMAL_AGREEMENT_COSINE`) with the
    normal most of them agree with.  At a corner a fused map smears (drift: a turned backrest's
    samples doubled a few centimetres apart where it meets the old one, normals leaning every
    way) the nearest span a few centimetres each way and fit a diagonal plane no surface lies
    on; among more samples, the surface most of them belong to is the one meeting the point.

    Returns
    -------
    found : ndarray, shape (b,), bool
        At least three such points.
    centroid, normal : ndarray, shape (b, 3)
    """
    k = min(DOMINANT_NEIGHBOURS if dominant else MEETING_NEIGHBOURS, other.points.shape[0])
    distance, index = other.geometry.tree.query(points, k=k, distance_upper_bound=reach)
    distance = np.asarray(distance).reshape(points.shape[0], k)
    index = np.minimum(np.asarray(index).reshape(points.shape[0], k), other.points.shape[0] - 1)
    normals = other.geometry.normal[index].astype(np.float64)
    candidate = (distance <= reach) & (
        np.abs(np.einsum("bkd,bd->bk", normals, toward)) < EDGE_COSINE
    )
    rows = np.arange(points.shape[0])
    if dominant:
        agree = np.abs(np.einsum("bkd,bjd->bkj", normals, normals)) >= NORMAL_AGREEMENT_COSINE
        agree &= candidate[:, :, None] & candidate[:, None, :]
        first = np.argmax(agree.sum(axis=2), axis=1)
        weight = agree[rows, first].astype(np.float64)
    else:
        weight = candidate.astype(np.float64)
        first = np.argmax(weight, axis=1)
    found = weight.sum(axis=1) >= 3
    centroid, values, vectors = weighted_plane(other.points[index], weight)
    normal = vectors[:, :, 0]
    # points along a line fit no plane: their mean normal then
    signs = np.where(np.einsum("bkd,bd->bk", normals, normals[rows, first]) < 0, -1.0, 1.0)
    mean = np.einsum("bk,bkd->bd", weight * signs, normals)
    mean /= np.maximum(np.linalg.norm(mean, axis=1), 1e-12)[:, None]
    flat = values[:, 1] >= 0.01 * values[:, 2]
    return found, centroid, np.where(flat[:, None], normal, mean)


def _joins(
    points: NDArray[np.float64],
    toward: NDArray[np.float64],
    depth: NDArray[np.float64],
    *,
    other: Side,
    change_threshold: float,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Which border points the other epoch's surface meets at an edge, and which of those it
    joins to the surface ``depth`` away along ``toward`` (the far face).

    The meeting surface (:func:`meeting_planes`) lies within :data:`EDGE_FACTOR` change
    thresholds of the point.  It joins the point to the far face when, on its plane, the other
    cloud has surface halfway towards the far face, none a margin past it, and none a margin
    behind the point: it runs from the part's edge to the far face and ends at both (an
    object's top or side).  The margin is the probe's radius (:data:`PROBE_SPACINGS` of the
    other cloud's local spacing) plus the change threshold.

    Parameters
    ----------
    points : ndarray, shape (b, 3)
    toward : ndarray, shape (b, 3)
        The part's unit normal, oriented towards the far face.
    depth : ndarray, shape (b,)
        The far face's distance from the part.
    other : Side
    change_threshold : float

    Returns
    -------
    meets, joins : ndarray, shape (b,), bool
    """
    count = points.shape[0]
    if count == 0:
        return np.zeros(0, dtype=bool), np.zeros(0, dtype=bool)
    reach = EDGE_FACTOR * change_threshold
    found, centroid, plane_normal = meeting_planes(points, toward, other, 2.0 * reach)
    height = np.einsum("bd,bd->b", points - centroid, plane_normal)
    meets = found & (np.abs(height) <= reach)
    foot = points - height[:, None] * plane_normal
    # the direction towards the far face, in the meeting surface's plane
    along = toward - np.einsum("bd,bd->b", toward, plane_normal)[:, None] * plane_normal
    along /= np.maximum(np.linalg.norm(along, axis=1), 1e-12)[:, None]
    _, nearest = other.geometry.tree.query(foot, k=1)
    spacing = other.geometry.spacing[np.asarray(nearest).ravel()]
    radius = np.maximum(PROBE_MIN_RADIUS, PROBE_SPACINGS * spacing)
    margin = radius + change_threshold
    halfway = _on_plane(
        foot + 0.5 * depth[:, None] * along, plane_normal, np.maximum(radius, 0.25 * depth), other
    )
    past_far_face = _on_plane(foot + (depth + margin)[:, None] * along, plane_normal, radius, other)
    behind_edge = _on_plane(foot - margin[:, None] * along, plane_normal, radius, other)
    return meets, meets & halfway & ~past_far_face & ~behind_edge


def _border(
    candidates: Candidates, chosen: NDArray[np.int64], own: Side, cluster_factor: float
) -> NDArray[np.bool_]:
    """Which ``chosen`` candidates have an own point that is no candidate within their
    cluster radius (shape (b,), bool)."""
    is_candidate = np.zeros(own.points.shape[0], dtype=bool)
    is_candidate[candidates.index] = True
    radius = cluster_factor * candidates.spacing[chosen]
    k = min(CLUSTER_NEIGHBOURS + 1, own.points.shape[0])
    distance, neighbour = own.geometry.tree.query(
        candidates.points[chosen], k=k, distance_upper_bound=float(radius.max())
    )
    distance = np.asarray(distance).reshape(chosen.shape[0], k)
    neighbour = np.minimum(
        np.asarray(neighbour).reshape(chosen.shape[0], k), own.points.shape[0] - 1
    )
    return ((distance <= radius[:, None]) & ~is_candidate[neighbour]).any(axis=1)


def far_faces(
    candidates: Candidates,
    labels: NDArray[np.int64],
    check: NDArray[np.bool_],
    *,
    own: Side,
    other: Side,
    counted: NDArray[np.bool_],
    threshold: float,
    change_threshold: float,
    cluster_factor: float,
) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
    """Per part, whether the other epoch's surface behind it is the far face of an object
    standing in both epochs, seen from its far side only (see the module's docstring).

    Parameters
    ----------
    candidates : Candidates
        ``own``'s change candidates.
    labels : ndarray, shape (c,), int64
        Their surface parts.
    check : ndarray, shape (parts,), bool
        The parts to look at (the others are False).
    own, other : Side
    counted : ndarray, shape (m,), bool
        The other cloud's points that count as surface behind (those this epoch lacks).
    threshold, change_threshold, cluster_factor : float
        ``tau``, the change threshold (metres) and the cluster linking factor.

    Returns
    -------
    far : ndarray, shape (parts,), bool
    share : ndarray, shape (parts,), float64
        Share of the part's border points met by the other epoch's surfaces at an edge that
        those surfaces join to the far face (0 for parts not checked).
    """
    n_parts = check.shape[0]
    far = np.zeros(n_parts, dtype=bool)
    chosen = np.flatnonzero(check[labels])
    if chosen.shape[0] == 0:
        return far, np.zeros(n_parts)
    axes = part_axes(candidates.normal[chosen], labels[chosen], n_parts)[labels[chosen]]
    ahead, back = oriented_depths(candidates.points[chosen], axes, other, counted)
    # the side of the part the surface behind lies on, and how far: per part, the majority
    hits_ahead = np.bincount(labels[chosen], weights=np.isfinite(ahead), minlength=n_parts)
    hits_back = np.bincount(labels[chosen], weights=np.isfinite(back), minlength=n_parts)
    sign = np.where(hits_ahead >= hits_back, 1.0, -1.0)
    depth = np.where(sign[labels[chosen]] > 0, ahead, back)
    found = np.isfinite(depth)
    part_depth = np.full(n_parts, np.inf)
    for part in np.unique(labels[chosen][found]):
        part_depth[part] = float(np.median(depth[found & (labels[chosen] == part)]))
    border = _border(candidates, chosen, own, cluster_factor)
    probe = np.flatnonzero(border & np.isfinite(part_depth[labels[chosen]]))
    part_of = labels[chosen[probe]]
    meets, joins = _joins(
        candidates.points[chosen[probe]],
        sign[part_of][:, None] * axes[probe],
        part_depth[part_of],
        other=other,
        change_threshold=change_threshold,
    )
    # the other epoch's samples in the air in front of the part meet no edge of it (map_sides)
    inward = inner_sides(candidates.points, candidates.normal, labels, check, other, counted)
    air = nearest_in_air(
        candidates.points[chosen[probe]], inward[chosen[probe]], other, counted, threshold
    )
    meets, joins = meets & ~air, joins & ~air
    meeting = np.bincount(part_of, weights=meets, minlength=n_parts)
    joining = np.bincount(part_of, weights=joins, minlength=n_parts)
    share = joining / np.maximum(meeting, 1.0)
    far = check & (joining >= MIN_JOINING) & (share >= FAR_FACE_SHARE)
    return far, share
