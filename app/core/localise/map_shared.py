"""Faces of objects standing in both epochs that only one epoch saw (:func:`unseen_faces`), and
level patches of a surface the other epoch saw elsewhere only (:func:`unseen_levels`)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from app.core.localise.map_parts import PartFigures

__all__ = ["MIN_ADJOINING", "SURROUND_SHARE", "unseen_faces", "unseen_levels"]

SURROUND_SHARE = 0.1
"""An upright part is an unseen side when less than this share of its adjoining border points
has the other epoch's surface carrying on past them (or surface this epoch lacks)."""
MIN_ADJOINING = 5
"""Fewer adjoining border points than this say nothing about a part."""
LEVEL_BEHIND_SHARE = 0.1
"""A level part with the other epoch's surface (that this epoch lacks) on the normal lines of
fewer than this share of its points has nothing under or over it that the other epoch saw."""
LEVEL_COPLANAR_SHARE = 0.5
"""... and with at least this share of its points on planes the other epoch has nearby, it is a
patch of a surface the other epoch saw elsewhere (:func:`unseen_levels`)."""
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
    at a part is no evidence either way (:func:`~app.core.localise.map_parts._supports`).
    Tops were left out before (s10): on six seeds of RGB-D rooms, horizontal parts meeting
    this rule carry 1,800 false changed points on unseen tops and desk strips and 71 true ones.
    A top is one only when the other epoch has no level surface straight under most of it
    within :data:`~app.core.localise.map_parts.SEE_THROUGH_REACH`
    (:func:`~app.core.localise.map_evidence._verdict`,
    :func:`~app.core.localise.map_planes.level_surface_below`): a solid object's body hides
    everything under its top, while under a removed table the other epoch saw the floor (the
    real classroom's table).  Until s12 that probe looked up as well and reached 1.42 m: it
    found the ceiling over a box's top as often as what lay under it.
    """
    return (figures.adjoining >= MIN_ADJOINING) & (figures.surround_share < SURROUND_SHARE)


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
