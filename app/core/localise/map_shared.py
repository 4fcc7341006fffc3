"""Surfaces both epochs saw in part: no see-through evidence for the map test.

A coverage difference (a part of this epoch's map lying on a surface that continues in the
other epoch) is still a change when the other epoch has surface that this epoch lacks on its
normal lines (:func:`~app.core.localise.map_parts.surface_behind`): the wall patch a box was
pushed out of, with the box's face now in front of it.  The other epoch's surface there is
evidence only when it is what changed.  Where it carries on, on its own plane, into surface
both epochs saw, it is a surface of both epochs that only the other one saw there: the top of
a desk standing in both, seen by the other path over a floor patch under it that only this
path saw.  Each epoch saw its own side of the desk top's edge; neither saw through the other.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from app.core.localise.distance import Side
from app.core.localise.gaps import NORMAL_AGREEMENT_COSINE, PLANE_SLOPE, tangent_directions
from app.core.localise.map_parts import PartFigures, near_candidates
from app.core.localise.settings import GATHER_CHUNK
from app.core.localise.surface import LocalGeometry

__all__ = ["SHARED_REACHES", "edge_strips", "partly_shared", "unshared"]

SHARED_REACHES = (0.1, 0.25, 0.5)
"""Metres: the other epoch's matched samples of a surface this far from one of its unmatched
points, on its plane (probed in :data:`SHARED_SECTORS` directions), make the surface one both
epochs saw."""
SHARED_SECTORS = 8
SHARED_NEIGHBOURS = 4


def partly_shared(
    index: NDArray[np.int64],
    cloud: LocalGeometry,
    lacking: NDArray[np.bool_],
    tolerance: float,
) -> NDArray[np.bool_]:
    """Whether each of ``cloud``'s points ``index`` (shape (p,)) lies on a surface that carries
    on, on the point's own plane, into ``cloud``'s points that the other epoch also has (not
    ``lacking``, shape (m,), bool) within the largest of :data:`SHARED_REACHES`: probed at each
    reach in :data:`SHARED_SECTORS` directions of the plane, a point of ``cloud`` within half
    the reach of the probe, within ``tolerance`` (plus
    :data:`~app.core.localise.gaps.PLANE_SLOPE` a metre) of the plane, with an agreeing normal;
    shape (p,), bool."""
    found = np.zeros(index.shape[0], dtype=bool)
    k = min(SHARED_NEIGHBOURS, cloud.points.shape[0])
    if index.shape[0] == 0 or k == 0:
        return found
    for start in range(0, index.shape[0], GATHER_CHUNK):
        chunk = index[start : start + GATHER_CHUNK]
        query = cloud.points[chunk]
        unit, directions = tangent_directions(cloud.normal[chunk], SHARED_SECTORS)
        hit = np.zeros(chunk.shape[0], dtype=bool)
        for reach in SHARED_REACHES:
            for sector in range(SHARED_SECTORS):
                probe = query + reach * directions[:, sector, :]
                distance, neighbour = cloud.tree.query(probe, k=k, distance_upper_bound=reach / 2)
                distance = np.asarray(distance).reshape(chunk.shape[0], k)
                neighbour = np.minimum(
                    np.asarray(neighbour).reshape(chunk.shape[0], k), cloud.points.shape[0] - 1
                )
                offset = cloud.points[neighbour] - query[:, None, :]
                along = np.linalg.norm(offset, axis=2)
                agrees = np.abs(
                    np.einsum("pkd,pd->pk", cloud.normal[neighbour].astype(np.float64), unit)
                )
                off_plane = np.abs(np.einsum("pkd,pd->pk", offset, unit))
                hit |= (
                    (distance <= reach / 2)
                    & (off_plane <= tolerance + PLANE_SLOPE * along)
                    & (agrees >= NORMAL_AGREEMENT_COSINE)
                    & ~lacking[neighbour]
                ).any(axis=1)
        found[start : start + GATHER_CHUNK] = hit
    return found


def edge_strips(
    part: PartFigures, *, min_adjoining: int, surround: float, coplanar: float
) -> NDArray[np.bool_]:
    """Per part, whether it is a strip of a face both epochs saw, along the face's edge
    (shape (parts,), bool): upright, on planes the other epoch has nearby (a ``coplanar``
    share of its points), with fewer than ``min_adjoining`` (but some) border points that the
    other epoch's surface meets at an edge, and that surface ending at them (a share under
    ``surround`` carries on).

    A sparse map sees an upright face in lidar columns, each epoch's elsewhere; a column next
    to the face's edge lies between the other epoch's columns on the face and the edge, where
    the other epoch's adjoining face (the object's side round the corner) ends.  Too few border
    points meet that side for an unseen side (the column is a few samples wide), and its
    half-plane towards the edge is empty
    (:func:`~app.core.localise.map_planes.in_sampling_gap`)."""
    return (
        part.upright
        & (part.adjoining >= 1)
        & (part.adjoining < min_adjoining)
        & (part.surround_share < surround)
        & (part.coplanar_share >= coplanar)
    )


def unshared(
    points: NDArray[np.float64],
    lacking: NDArray[np.bool_],
    counted: NDArray[np.bool_],
    other: Side,
    tolerance: float,
) -> NDArray[np.bool_]:
    """The other cloud's points that this epoch lacks (``lacking``, shape (m,), bool) and that
    may be see-through evidence (``counted``, shape (m,)), without those that the probes from
    ``points`` (shape (c, 3)) reach and that lie on a surface both epochs saw in part
    (:func:`partly_shared`); shape (m,), bool."""
    evidence = lacking & counted
    reached = near_candidates(points, other, evidence)
    evidence[reached[partly_shared(reached, other.geometry, lacking, tolerance)]] = False
    return evidence
