"""Faces both epochs saw in part: strips of a face along its edge are unseen sides.

A sparse map sees an upright face in lidar columns, each epoch's elsewhere.  A column next to
the face's edge lies between the other epoch's columns on the face and the edge, where the
other epoch's side round the corner ends (:func:`edge_strips`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from app.core.localise.map_parts import PartFigures

__all__ = ["edge_strips"]


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
