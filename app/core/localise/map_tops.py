"""The map test's level tops held up in both epochs: a desk top one path never saw.

A sparse robot map may see an open desk's top from one path only (the other passed it with the
lidar level with the top, or out of reach of its lower rings) and its legs and the floor under
it from both.  The floor under the top says the other epoch saw past the top's place, as under
a removed table, so the top stays a change (robot office 2002: a 1.4 x 0.8 m desk top, 384
false points).  What tells them apart is what stands between the two: a removed table's legs
are gone from the other epoch, an unseen top's legs are there in both.  A level part is held
(:func:`held_tops`) when the other epoch has points it shares with this one (matched within the
change threshold) under the part, above the first level surface the other epoch has under it
and below the part's own height, that end below it (no point of the other epoch over them up to
:data:`ABOVE_REACH` over the part: a wall beside a removed box carries on over its top), in at
least two posts (each at most :data:`POST_WIDTH` wide) :data:`MIN_SPREAD` apart: a wall strip the
other epoch saw only under the part's height is no post.  A box removed from a desk top has the
desk top as that first level surface and nothing between; a removed chair's legs are gone with
it.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.localise.distance import Side
from app.core.localise.map_parts import UPRIGHT_NORMAL_Z, PartFigures
from app.core.localise.rays import Candidates
from app.core.localise.regions import cluster_labels

__all__ = ["ABOVE_REACH", "MIN_HELD_POINTS", "MIN_SPREAD", "held_tops", "with_held_tops"]

BELOW_REACH = 1.2
"""Metres under a part's height in which the other epoch's points are looked at."""
ABOVE_REACH = 0.5
"""Metres over a part's height in which the other epoch's points make a holding point none."""
MIN_HELD_POINTS = 6
"""Holding points a part needs."""
MIN_SPREAD = 0.3
"""Metres: two posts holding the part stand at least this far apart horizontally (two legs, not
one)."""
POST_WIDTH = 0.25
"""Metres: a post (a leg, a pedestal) holding a top is at most this wide horizontally.  A wall
strip under a removed chair's seat, seen in the other epoch below the seat's height only (the
wall over the seat unseen there), is wider: it holds nothing up (RGB-D room 800: the removed
chair 98 -> 0 % without this)."""
MIN_POST_POINTS = 3
"""Holding points a post needs."""
POST_LINK_SPACINGS = 3.0
"""Holding points within this many of the other cloud's spacings of each other, horizontally,
are one post."""
LINE_SPREAD = 0.25
LINE_REACH = 0.5
"""Metres: a level part that is a line (a desk's front rim seen by one path only, at its
lidar's height) is held by posts along it past its ends up to this far: its top's points
next to the legs are within the change threshold of the legs' tops and no candidates."""
LEVEL_SURFACE_SHARE = 0.2
"""Level points of the other epoch within half the change threshold of one height, as many as
this share of the part's points (and 5 at least), make it a level surface under the part (a
leg's few points with a level normal fitted round its corners are none)."""


def _line_ends(part_points: NDArray[np.float64], step: float) -> NDArray[np.float64]:
    """The part's points (shape (p, 3)) and, for a part that is a line horizontally (spread
    across under :data:`LINE_SPREAD` of the spread along), places every ``step`` metres along
    it past each end up to :data:`LINE_REACH`, at its median height; shape (q, 3)."""
    if part_points.shape[0] < 3:
        return part_points
    flat = part_points[:, :2] - part_points[:, :2].mean(axis=0)
    _, _, axes = np.linalg.svd(flat, full_matrices=False)
    along, across = flat @ axes[0], flat @ axes[1]
    if np.ptp(across) > LINE_SPREAD * np.ptp(along):
        return part_points
    reach = np.arange(step, LINE_REACH + step / 2.0, step)
    ends = np.concatenate([along.min() - reach, along.max() + reach])
    places = part_points[:, :2].mean(axis=0) + ends[:, None] * axes[0]
    height = np.full((ends.shape[0], 1), np.median(part_points[:, 2]))
    return np.vstack([part_points, np.hstack([places, height])])


def _under_part(
    part_points: NDArray[np.float64], other: Side, radius: float, height: float
) -> NDArray[np.int64]:
    """Indices of the other cloud's points within ``radius`` horizontally of one of the part's
    points (shape (p, 3)) and within :data:`BELOW_REACH` under to :data:`ABOVE_REACH` over its
    ``height``; shape (u,)."""
    low, high = part_points.min(axis=0), part_points.max(axis=0)
    box = np.flatnonzero(
        np.all(other.points[:, :2] >= low[:2] - radius, axis=1)
        & np.all(other.points[:, :2] <= high[:2] + radius, axis=1)
        & (other.points[:, 2] >= height - BELOW_REACH)
        & (other.points[:, 2] <= height + ABOVE_REACH)
    )
    if box.shape[0] == 0:
        return box
    distance, _ = KDTree(np.ascontiguousarray(part_points[:, :2])).query(
        np.ascontiguousarray(other.points[box, :2]), k=1
    )
    return box[distance <= radius]


def _holding(
    part_points: NDArray[np.float64],
    other: Side,
    other_unmatched: NDArray[np.bool_],
    change_threshold: float,
    radius: float,
) -> bool:
    """Whether the other epoch holds the level part (points shape (p, 3)) up with surface both
    epochs have (:func:`held_tops`)."""
    height = float(np.median(part_points[:, 2]))
    under = _under_part(_line_ends(part_points, radius), other, radius, height)
    z = other.points[under, 2]
    level = np.abs(other.geometry.normal[under, 2]) >= 1.0 - UPRIGHT_NORMAL_Z / 2.0
    below = z < height - change_threshold
    level_z = np.sort(z[level & below])
    counts = np.searchsorted(level_z, level_z + change_threshold / 2.0, side="right")
    counts -= np.searchsorted(level_z, level_z - change_threshold / 2.0, side="left")
    surfaces = level_z[counts >= max(5.0, LEVEL_SURFACE_SHARE * part_points.shape[0])]
    floor = float(surfaces.max()) if surfaces.shape[0] else float(z.min(initial=height))
    band = below & (z > floor + change_threshold) & ~other_unmatched[under]
    if np.count_nonzero(band) < MIN_HELD_POINTS:
        return False
    over = other.points[under[z > height + change_threshold], :2]
    held = other.points[under[band], :2]
    if over.shape[0]:
        distance, _ = KDTree(np.ascontiguousarray(over)).query(np.ascontiguousarray(held), k=1)
        held = held[distance > radius]
    if held.shape[0] < MIN_HELD_POINTS:
        return False
    return _two_posts(held, POST_LINK_SPACINGS * (radius - change_threshold))


def _two_posts(held: NDArray[np.float64], link: float) -> bool:
    """Whether the holding points (horizontal positions, shape (h, 2)) form two posts, each at
    most :data:`POST_WIDTH` wide, :data:`MIN_SPREAD` apart or more (points within ``link`` of
    each other are one post)."""
    flat = np.column_stack([held, np.zeros(held.shape[0])])
    post = cluster_labels(flat, np.full(held.shape[0], link))
    centres = [
        members.mean(axis=0)
        for members in (held[post == label] for label in np.unique(post))
        if members.shape[0] >= MIN_POST_POINTS and np.max(np.ptp(members, axis=0)) <= POST_WIDTH
    ]
    if len(centres) < 2:
        return False
    centre = np.asarray(centres)
    apart = np.linalg.norm(centre[:, None, :] - centre[None, :, :], axis=2)
    return bool(apart.max() >= MIN_SPREAD)


def held_tops(
    points: NDArray[np.float64],
    labels: NDArray[np.int64],
    check: NDArray[np.bool_],
    *,
    other: Side,
    other_unmatched: NDArray[np.bool_],
    change_threshold: float,
) -> NDArray[np.bool_]:
    """Per part, whether it is a level top that the other epoch holds up with surface both
    epochs have (shape (parts,), bool; only parts marked in ``check`` are tried).

    "Under" the part is within the change threshold and one of the other cloud's spacings of
    one of its points, horizontally: the top's points within the change threshold of its legs
    are no candidates, so the legs stand that far from the part's points.

    Parameters
    ----------
    points : ndarray, shape (c, 3)
        The candidates.
    labels : ndarray, shape (c,), int64
        Each candidate's part.
    check : ndarray, shape (parts,), bool
        The level parts to try (those still called changes).
    other : Side
        The other epoch.
    other_unmatched : ndarray, shape (m,), bool
        The other epoch's points this one lacks (they hold nothing up).
    change_threshold : float
        ``c``, metres.

    Returns
    -------
    ndarray, shape (parts,), bool
    """
    held = np.zeros(check.shape[0], dtype=bool)
    radius = change_threshold + float(np.median(other.geometry.spacing))
    for part in np.flatnonzero(check):
        part_points = points[labels == part]
        held[part] = _holding(part_points, other, other_unmatched, change_threshold, radius)
    return held


def with_held_tops(
    candidates: Candidates,
    labels: NDArray[np.int64],
    figures: PartFigures,
    coverage: NDArray[np.bool_],
    confidence: NDArray[np.float64],
    other: Side,
    other_unmatched: NDArray[np.bool_],
    c: float,
) -> tuple[NDArray[np.bool_], NDArray[np.float64], int]:
    """The map test's verdict (``coverage`` and ``confidence`` per part, shapes (parts,)) with the
    near level parts of :data:`MIN_HELD_POINTS` or more still called changes that
    :func:`held_tops` holds up made coverage differences (confidence 0.5), and their count.
    ``labels`` (shape (c,)) gives each candidate's part; ``c`` is the change threshold."""
    level = figures.near & ~figures.upright & ~coverage & (figures.sizes >= MIN_HELD_POINTS)
    held = held_tops(
        candidates.points,
        labels,
        level,
        other=other,
        other_unmatched=other_unmatched,
        change_threshold=c,
    )
    return coverage | held, np.where(held, 0.5, confidence), int(held.sum())
