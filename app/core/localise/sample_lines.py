"""Samples on one line: where a fitted normal says nothing, and what a line does say.

A sparse map (a robot's 16-ring lidar) sees a desk top or a box top far from its path as single
ring arcs along its rim.  A sample's nearest others then lie on one line, and a plane fitted
there is any plane through the line; widened (:func:`~app.core.localise.surface.fit_surfaces`
refits such neighbourhoods with three times the neighbours) it may take in a second line, the
floor's arc 0.7 m under the rim, and fit an upright plane through both that no surface holds.
The rim arc of a level top then seems to carry on an upright face standing on the top, and not
to carry on the top itself.

A line says only this: the surface holds the line.  A surface of the other epoch continues
through a sample on a line when the line lies in the surface's plane and the sample is itself
within the change threshold of that surface's own points (a line cannot vouch for the plane it
is fitted to across it).  Whether a sample is on a line is read from its own nearest samples,
the neighbourhood its normal was first fitted over, not from the widened one.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from app.core.localise.gaps import NORMAL_AGREEMENT_COSINE
from app.core.localise.surface import LINEAR_EIGENVALUE_RATIO, LocalGeometry

__all__ = ["LINE_NEIGHBOURS", "continues_into", "lines_in_planes", "sample_lines"]

LINE_NEIGHBOURS = 11
"""A sample and its nearest others that tell whether it lies on a line (the neighbourhood of
the default ``n_neighbors`` = 10 a normal is first fitted over)."""
IN_PLANE_SINE = math.sqrt(1.0 - NORMAL_AGREEMENT_COSINE**2)
"""A line lies in a plane when its direction is within the normals' agreement angle of it."""


def sample_lines(
    cloud: LocalGeometry, index: NDArray[np.integer]
) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
    """Whether each of the ``cloud``'s samples ``index`` (shape (m,)) lies on a line with its
    :data:`LINE_NEIGHBOURS` nearest samples
    (:data:`~app.core.localise.surface.LINEAR_EIGENVALUE_RATIO`), and that line's direction.

    Returns
    -------
    on_line : ndarray, shape (m,), bool
    direction : ndarray, shape (m, 3), float64
        Unit vectors (the principal axis of the neighbourhood, line or not).
    """
    count = index.shape[0]
    k = min(LINE_NEIGHBOURS, cloud.points.shape[0])
    if count == 0 or k < 3:
        return np.zeros(count, dtype=bool), np.zeros((count, 3))
    _, neighbours = cloud.tree.query(cloud.points[index], k=k)
    gathered = cloud.points[np.asarray(neighbours).reshape(count, k)]
    centred = gathered - gathered.mean(axis=1, keepdims=True)
    values, vectors = np.linalg.eigh(np.einsum("mki,mkj->mij", centred, centred))
    on_line = values[:, 1] < LINEAR_EIGENVALUE_RATIO * np.maximum(values[:, 2], 1e-18)
    return on_line, vectors[:, :, 2]


def lines_in_planes(
    cloud: LocalGeometry,
    index: NDArray[np.integer],
    unit: NDArray[np.float64],
    consider: NDArray[np.bool_],
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Which samples ``index`` of ``cloud`` marked in ``consider`` lie on a line
    (:func:`sample_lines`), and which of those lines lie in their row's plane (normal
    ``unit``, within the normals' agreement angle).

    Parameters
    ----------
    cloud : LocalGeometry
    index : ndarray, shape (p, k), int
    unit : ndarray, shape (p, 3)
        Unit normals of the planes.
    consider : ndarray, shape (p, k), bool

    Returns
    -------
    on_line, in_plane : ndarray, shape (p, k), bool
        False where not considered.
    """
    on_line = np.zeros(consider.shape, dtype=bool)
    in_plane = np.zeros(consider.shape, dtype=bool)
    if not consider.any():
        return on_line, in_plane
    samples, inverse = np.unique(index[consider], return_inverse=True)
    sample_on_line, direction = sample_lines(cloud, samples)
    rows = np.nonzero(consider)[0]
    on_line[consider] = sample_on_line[inverse]
    in_plane[consider] = on_line[consider] & (
        np.abs(np.einsum("pd,pd->p", direction[inverse], unit[rows])) <= IN_PLANE_SINE
    )
    return on_line, in_plane


def continues_into(
    unit: NDArray[np.float64],
    own_points: NDArray[np.float64],
    match: NDArray[np.integer],
    consider: NDArray[np.bool_],
    own: LocalGeometry,
    other: LocalGeometry,
    change_threshold: float,
    anchor: NDArray[np.float64] | None = None,
) -> NDArray[np.bool_]:
    """Whether the other epoch's sample ``match`` carries on the plane of normal ``unit``
    through this epoch's point ``own_points``: parallel to it and on it, or, on a line
    (:func:`sample_lines`), holding the line in the plane and within ``change_threshold`` of
    the point.  With ``anchor`` (the row's own point whose plane it is), the sample's plane
    must also pass within ``change_threshold`` of the anchor: a surface carries on through a
    gap in its own plane, and one that passes the anchor farther off is another surface
    (a chair's back tilted 5-13 cm before a wall, its points nearest the wall matched to it:
    robot 2804).

    Parameters
    ----------
    unit : ndarray, shape (c, 3)
        Unit normals of the plane, one per row.
    own_points : ndarray, shape (c, k, 3)
        This epoch's points (each row's neighbours).
    match : ndarray, shape (c, k), int
        Their nearest samples in ``other``.
    consider : ndarray, shape (c, k), bool
        The pairs worth judging (others are False).
    other : LocalGeometry
    change_threshold : float
    anchor : ndarray, shape (c, 3), optional

    Returns
    -------
    ndarray, shape (c, k), bool
    """
    offset = other.points[match] - own_points
    parallel = np.abs(np.einsum("ckd,cd->ck", other.normal[match], unit)) >= NORMAL_AGREEMENT_COSINE
    on_it = consider & (np.abs(np.einsum("ckd,cd->ck", offset, unit)) <= change_threshold)
    on_line, in_plane = lines_in_planes(other, match, unit, on_it)
    held = in_plane & (np.linalg.norm(offset, axis=2) <= change_threshold)
    if held.any():
        # which plane through the line: this epoch's own surface where the line lies
        _, own_there = own.tree.query(other.points[match[held]], k=1)
        rows = np.nonzero(held)[0]
        held[held] = (
            np.abs(np.einsum("pd,pd->p", own.normal[np.asarray(own_there).ravel()], unit[rows]))
            >= NORMAL_AGREEMENT_COSINE
        )
    carried = on_it & np.where(on_line, held, parallel)
    if anchor is not None:
        # the sample's plane carried on to the anchor (a line's: the own plane through it)
        past = other.points[match] - anchor[:, None, :]
        plane = np.where(on_line[:, :, None], unit[:, None, :], other.normal[match])
        carried &= np.abs(np.einsum("ckd,ckd->ck", past, plane)) <= change_threshold
    return carried
