"""Whether the other epoch's surface adjoins a border point of a map part at an edge, and
whether it carries on past the point or ends at it (:func:`surrounded`): the map test's
evidence that the other epoch saw the part's object, or its place
(:mod:`app.core.localise.map_parts` gathers it per part)."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from app.core.localise.gaps import NORMAL_AGREEMENT_COSINE, PLANE_SLOPE, tangent_directions
from app.core.localise.map_planes import SECTORS, holds_up, shared_wall, through_lacking
from app.core.localise.map_sides import in_front
from app.core.localise.settings import GATHER_CHUNK
from app.core.localise.surface import LocalGeometry

__all__ = [
    "ADJOINING_FACTOR",
    "EDGE_COSINE",
    "SURROUND_REACH",
    "SURROUND_SECTORS",
    "UPRIGHT_NORMAL_Z",
    "surrounded",
]

SURROUND_NEIGHBOURS = 32
"""The other epoch's points looked at around a border point's foot on its adjoining surface."""
SURROUND_REACH = 0.5
"""Metres: farther points of the adjoining surface say nothing about the border point."""
ADJOINING_FACTOR = 2.0
"""The other epoch's surface adjoins a border point within this many change thresholds."""
SURROUND_SECTORS = 6
"""The adjoining surface carries on past a border point when it lies in this many of
:data:`SECTORS` directions around the point's foot."""
EDGE_COSINE = math.cos(math.radians(60.0))
"""A surface adjoins a border point at an edge when the normals' cosine is below this."""
UPRIGHT_NORMAL_Z = 0.5
"""A part is upright (a side) when its normals' mean vertical component is below this."""


def _supports(unit: NDArray[np.float64], height: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Whether the other epoch's adjoining surface is a level one under the point (a floor, a
    seat, a desk top the part stands on); shapes (b, 3), (b,) -> (b,).

    A supporting surface that ends at an upright part says nothing of whether the part stood
    in the other epoch: the floor in front of a box ends at its side because the box hides
    the floor under it, and a chair's seat ends where its backrest rises, whichever way the
    chair was turned.  Such border points do not count as adjoined (:func:`surrounded`); a
    support that carries on past the part (the floor under an added box's place) still does.
    The surfaces that end at a part's upper and side edges (the object's top, its other
    faces) are the evidence: the other epoch saw the object's other surfaces meet this one.
    """
    level = np.abs(unit[:, 2]) >= NORMAL_AGREEMENT_COSINE
    return level & (height * np.sign(unit[:, 2]) > 0.0)


def _clear_of_edge(
    offset: NDArray[np.float64],
    own_normal: NDArray[np.floating],
    unit: NDArray[np.float64],
    margin: float,
) -> NDArray[np.bool_]:
    """Which offsets on the adjoining plane lie farther than ``margin`` from the line where
    the point's own surface meets that plane (shapes (b, k, 3), (b, 3), (b, 3) -> (b, k)).

    A surface that ends at the point's edge (a box's side under the rim of its top) has its
    last rows of samples along that line, spread a little to both sides by noise: counted,
    they fill the directions next to the line on the far side as well, and the surface seems
    to carry on past the point (6 of 8 directions where a half-plane fills 4).  Only samples
    clear of the line tell on which sides of it the surface lies.  Not for a support
    (:func:`_supports`): under a thin part (a backrest turned on its seat) the seat carries
    on past its foot by the part's thickness only, a few centimetres."""
    edge = np.cross(own_normal.astype(np.float64), unit)
    edge /= np.maximum(np.linalg.norm(edge, axis=1), 1e-12)[:, None]
    across = np.cross(unit, edge)
    return np.abs(np.einsum("bkd,bd->bk", offset, across)) > margin


def surrounded(
    points: NDArray[np.float64],
    own_normal: NDArray[np.floating],
    other: LocalGeometry,
    other_unmatched: NDArray[np.bool_],
    tolerance: float,
    change_threshold: float,
    inward: NDArray[np.float64],
) -> tuple[NDArray[np.bool_], NDArray[np.int64], NDArray[np.bool_]]:
    """Whether the other epoch's surface adjoins each border point at an edge, in how many
    directions it carries on past the point, and whether it lies wholly under the point.

    The other epoch's nearest surface (within :data:`ADJOINING_FACTOR` change thresholds, at
    an angle to the point's own: :data:`EDGE_COSINE`) is taken as the plane of its nearest
    point; the point is projected onto it, and that plane's points around the projection (the
    :data:`SURROUND_NEIGHBOURS` nearest within :data:`SURROUND_REACH`) are sorted into
    :data:`SECTORS` directions.  Where the other epoch saw the place of a removed or added
    object, its floor, desk top or wall carries on under it: the directions are all taken (and
    where that surface is one this epoch lacks, the object hid it: all directions count).
    Where the object stands in both epochs and only this epoch faced one of its sides, the
    other epoch's surfaces next to that side (the object's top, the floor in front of it) end
    at it: half the directions are empty.

    Parameters
    ----------
    points : ndarray, shape (b, 3)
    own_normal : ndarray, shape (b, 3)
        The points' own surface normals.
    other : LocalGeometry
    other_unmatched : ndarray, shape (m,), bool
        The other epoch's points that this epoch lacks.
    tolerance, change_threshold : float
        The plane tolerance and the change threshold (metres).
    inward : ndarray, shape (b, 2, 3)
        Unit directions into each point's part (zero: not known,
        :func:`~app.core.localise.map_sides.inner_sides`).

    Returns
    -------
    adjoining : ndarray, shape (b,), bool
        Whether the other epoch has a surface meeting the point's at an edge next to it (not
        one the point stands on that ends there: :func:`_supports`).
    sectors : ndarray, shape (b,), int64
        In how many of :data:`SECTORS` directions that surface carries on past the point.
    under : ndarray, shape (b,), bool
        That surface is an upright one lying wholly under an upright point
        (:func:`~app.core.localise.map_planes.holds_up`).
    """
    count = points.shape[0]
    adjoining = np.zeros(count, dtype=bool)
    sectors = np.zeros(count, dtype=np.int64)
    under = np.zeros(count, dtype=bool)
    if count == 0:
        return adjoining, sectors, under
    k = min(SURROUND_NEIGHBOURS, other.points.shape[0])
    for start in range(0, count, GATHER_CHUNK):
        chunk = slice(start, start + GATHER_CHUNK)
        adjoining[chunk], sectors[chunk], under[chunk] = _surrounded_chunk(
            points[chunk],
            own_normal[chunk],
            other,
            other_unmatched,
            tolerance=tolerance,
            change_threshold=change_threshold,
            inward=inward[chunk],
            k=k,
        )
    return adjoining, sectors, under


def _surrounded_chunk(
    query: NDArray[np.float64],
    own_normal: NDArray[np.floating],
    other: LocalGeometry,
    other_unmatched: NDArray[np.bool_],
    *,
    tolerance: float,
    change_threshold: float,
    inward: NDArray[np.float64],
    k: int,
) -> tuple[NDArray[np.bool_], NDArray[np.int64], NDArray[np.bool_]]:
    """:func:`surrounded` for one chunk of border points ``query`` (shape (c, 3)), with their
    ``k`` nearest points of the other epoch."""
    distance, index = other.tree.query(query, k=k)
    distance = np.asarray(distance).reshape(query.shape[0], k)
    index = np.asarray(index).reshape(query.shape[0], k)
    nearest = index[:, 0]
    unit = other.normal[nearest].astype(np.float64)
    height = np.einsum("cd,cd->c", query - other.points[nearest], unit)
    # only a surface meeting the point's own at an edge adjoins it: one parallel to it
    # is a gap in a surface both have, or a surface under or over it
    across = np.abs(np.einsum("cd,cd->c", own_normal.astype(np.float64), unit)) < EDGE_COSINE
    adjoining = (np.abs(height) <= ADJOINING_FACTOR * change_threshold) & across
    support = _supports(unit, height)
    foot = query - height[:, None] * unit
    offset = other.points[index] - foot[:, None, :]
    along = np.linalg.norm(offset, axis=2)
    on_plane = (
        (distance <= SURROUND_REACH)
        & (np.abs(np.einsum("ckd,cd->ck", offset, unit)) <= tolerance + PLANE_SLOPE * along)
        & (
            np.abs(np.einsum("ckd,cd->ck", other.normal[index].astype(np.float64), unit))
            >= NORMAL_AGREEMENT_COSINE
        )
        & (_clear_of_edge(offset, own_normal, unit, tolerance) | support[:, None])
    )
    sectors = _sectors_taken(offset, on_plane, unit)
    under = holds_up(offset, on_plane, own_normal, unit, tolerance, UPRIGHT_NORMAL_Z)
    # a wall both epochs saw on both sides of the point: no face of its object, no evidence
    shared = shared_wall(offset, on_plane, index, own_normal, unit, other_unmatched)
    adjoining &= ~shared | other_unmatched[nearest]
    # a surface that this epoch lacks next to the point: the object hid it here; not in
    # front of the part, though, in the air this epoch saw it through (map_sides.in_front)
    lacking = other_unmatched[nearest]
    air = lacking & in_front(other.points[nearest] - query, inward, tolerance)
    sectors[lacking & ~air] = SECTORS
    # ... or on the far side of the point's surface, that surface crossing it
    ahead = np.einsum("ckd,csd->cks", other.points[index] - query[:, None, :], inward)
    marked = other_unmatched[index] & ~(ahead < -tolerance).any(axis=2)
    crossing = through_lacking(offset, on_plane, marked, own_normal, unit)
    sectors[crossing] = SECTORS
    adjoining &= ~air
    adjoining &= ~(support & (sectors < SURROUND_SECTORS))
    return adjoining, sectors, under


def _sectors_taken(
    offset: NDArray[np.float64], on_plane: NDArray[np.bool_], unit: NDArray[np.float64]
) -> NDArray[np.int64]:
    """In how many of :data:`SECTORS` directions round each foot on the plane of normal
    ``unit`` (shape (c, 3)) the ``on_plane`` samples (``offset`` from the foot, shapes
    (c, k, 3), (c, k)) lie; shape (c,)."""
    _, directions = tangent_directions(unit, 4)
    first, second = directions[:, 0, :], directions[:, 1, :]
    angle = np.arctan2(
        np.einsum("ckd,cd->ck", offset, second), np.einsum("ckd,cd->ck", offset, first)
    )
    sector = np.floor((angle + math.pi) / (2.0 * math.pi) * SECTORS).astype(np.int64)
    sector = np.clip(sector, 0, SECTORS - 1)
    taken = np.zeros((offset.shape[0], SECTORS), dtype=bool)
    rows = np.broadcast_to(np.arange(offset.shape[0])[:, None], sector.shape)
    taken[rows[on_plane], sector[on_plane]] = True
    return taken.sum(axis=1)
