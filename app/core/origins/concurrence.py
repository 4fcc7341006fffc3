"""Points where the top-view lines of neighbour pairs concur: the (x, y) of lidar stations.

An upright spinning lidar fires each column in a vertical half-plane through its axis, and
range noise moves a return along its ray: two neighbouring returns of one column lie, in the
top view, on a line through the station's (x, y) exactly.  Used by
:mod:`app.core.origins.stations`.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree
from scipy.ndimage import maximum_filter, uniform_filter

__all__ = ["MAX_STATIONS", "column_centres", "search_centres"]

PAIR_NEIGHBOURS = 4
MAX_PAIR_LENGTH = 0.5
MIN_HORIZONTAL_SHARE = 0.3
"""A pair whose top-view part is shorter than this share of its length gives no line."""
MAX_LINES = 30_000
PAIR_QUERIES = 40_000
"""Points (a seeded random share) whose neighbour pairs are made into lines."""
VOTE_REACH = 10.0
"""Each line votes within this many metres of its pair (a lidar's dense returns are near it)."""
MIN_VOTE_DISTANCE = 0.3
"""Nor nearer than this: every line passes through its own pair, so dense patches of returns
(a lidar's first rings on the floor) would otherwise outvote the stations."""
CELL = 0.02
"""Hough cell (metres): fine, so that the few lines of a station hidden among others' still
stand out of the lines that pass by chance."""
PEAK_SEPARATION = 7
"""A Hough peak is the largest of this many cells square around it."""
MAX_CANDIDATES = 60
"""Hough peaks refined and tested per pass (most are not stations)."""
MAX_STATIONS = 8
MIN_CONCURRING = 50
CONCUR_DISTANCE = 0.003
"""A line concurs with a station when it passes within this many metres of it (column lines
are exact: range noise moves a return along its ray)."""
BACKGROUND_DISTANCE = 0.03
"""Lines passing 3-30 mm from a candidate estimate the chance concurrences at it."""
MIN_SIGNIFICANCE = 8.0
"""A candidate's concurring lines, less the chance ones, must exceed this many standard
deviations (Poisson) of the chance count."""
MIN_SEPARATION = 0.03
"""Candidates closer than this (metres, top view) to a kept station are that station."""
REFINE_LINES = 3000
"""Lines near a peak that its refinement uses (the first ones, in the lines' seeded order)."""
MIN_NORMAL_Z = 0.5
"""Only pairs on floors, ceilings and tops (normal within 60 degrees of vertical) give lines:
ring pairs on a wall give lines along the wall, which all concur with each other."""


def _pair_lines(
    points: NDArray[np.float64], rng: np.random.Generator
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Top-view lines of neighbour pairs: anchors (l, 2) and unit directions (l, 2)."""
    if points.shape[0] < PAIR_NEIGHBOURS + 4:
        return np.empty((0, 2)), np.empty((0, 2))
    tree_points = points
    tree = KDTree(tree_points)
    if points.shape[0] > PAIR_QUERIES:  # enough lines from a seeded share of the points
        points = points[np.sort(rng.choice(points.shape[0], PAIR_QUERIES, replace=False))]
    distance, index = tree.query(points, k=max(PAIR_NEIGHBOURS + 1, 8))
    neighbourhood = tree_points[index] - tree_points[index].mean(axis=1, keepdims=True)
    _, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", neighbourhood, neighbourhood))
    level = np.abs(vectors[:, 2, 0]) >= MIN_NORMAL_Z
    distance, index = distance[:, : PAIR_NEIGHBOURS + 1], index[:, : PAIR_NEIGHBOURS + 1]
    offset = tree_points[index[:, 1:]] - points[:, None, :]  # (n, k, 3)
    length = distance[:, 1:]
    horizontal = np.hypot(offset[..., 0], offset[..., 1])
    usable = (
        level[:, None]
        & (length > 0)
        & (length <= MAX_PAIR_LENGTH)
        & (horizontal >= MIN_HORIZONTAL_SHARE * length)
    )
    rows, columns = np.nonzero(usable)
    if rows.size > MAX_LINES:
        pick = np.sort(rng.choice(rows.size, MAX_LINES, replace=False))
        rows, columns = rows[pick], columns[pick]
    anchor = points[rows, :2]
    direction = offset[rows, columns, :2] / horizontal[rows, columns, None]
    order = rng.permutation(rows.size)  # refinements take the first lines near a peak
    return anchor[order], direction[order]


def _distance_to_lines(anchor: NDArray, direction: NDArray, centre: NDArray) -> NDArray:
    """Perpendicular top-view distance of ``centre`` (2,) to each line, shape (l,)."""
    relative = centre - anchor
    return np.abs(relative[:, 0] * direction[:, 1] - relative[:, 1] * direction[:, 0])


def _least_squares_point(anchor: NDArray, direction: NDArray) -> NDArray[np.float64]:
    """The point nearest (least squares) to all the lines, shape (2,)."""
    normal = np.column_stack([-direction[:, 1], direction[:, 0]])
    matrix = normal.T @ normal
    vector = normal.T @ np.einsum("ld,ld->l", normal, anchor)
    return np.linalg.solve(matrix + 1e-12 * np.eye(2), vector)


def _refined_centre(anchor: NDArray, direction: NDArray, centre: NDArray) -> NDArray:
    """A Hough peak made exact: the densest concurrence on finer grids, then least squares."""
    for reach, step, band in ((2.5 * CELL, 0.005, 0.005), (0.006, 0.001, 0.002)):
        near = np.flatnonzero(_distance_to_lines(anchor, direction, centre) <= reach + band)
        near = near[:REFINE_LINES]
        if near.size < 2:
            return centre
        offsets = np.arange(-reach, reach + 1e-9, step)
        grid = centre + np.stack(np.meshgrid(offsets, offsets, indexing="ij"), -1).reshape(-1, 2)
        relative = grid[:, None, :] - anchor[None, near, :]
        distance = np.abs(
            relative[..., 0] * direction[near, 1] - relative[..., 1] * direction[near, 0]
        )
        centre = grid[int(np.argmax((distance <= band).sum(axis=1)))]
    close = _distance_to_lines(anchor, direction, centre) <= CONCUR_DISTANCE
    if close.sum() >= 2:
        centre = _least_squares_point(anchor[close], direction[close])
    return centre


def _hough_peaks(
    points: NDArray[np.float64], anchor: NDArray, direction: NDArray
) -> NDArray[np.float64]:
    """Top-view cells where many lines cross, strongest first, shape (c, 2)."""
    low = points[:, :2].min(axis=0) - 1.0
    shape = np.ceil((points[:, :2].max(axis=0) + 1.0 - low) / CELL).astype(np.int64) + 1
    # in cell units, single precision: the vote is the costly part of a search
    steps = np.arange(MIN_VOTE_DISTANCE / CELL, VOTE_REACH / CELL, dtype=np.float32)
    steps = np.concatenate([-steps[::-1], steps])
    start_cell = ((anchor - low) / CELL).astype(np.float32)
    direction32 = direction.astype(np.float32)
    votes = np.zeros(int(shape[0] * shape[1]))
    for start in range(0, anchor.shape[0], 1024):
        part = slice(start, start + 1024)
        row = start_cell[part, 0, None] + steps * direction32[part, 0, None]
        column = start_cell[part, 1, None] + steps * direction32[part, 1, None]
        inside = (row >= 0) & (row < shape[0]) & (column >= 0) & (column < shape[1])
        flat = row[inside].astype(np.int64) * shape[1] + column[inside].astype(np.int64)
        votes += np.bincount(flat, minlength=votes.size)
    smoothed = uniform_filter(votes.reshape(shape), size=3, mode="constant")
    peaks = (smoothed == maximum_filter(smoothed, size=PEAK_SEPARATION, mode="constant")) & (
        smoothed > 0
    )
    flat = np.flatnonzero(peaks.ravel())
    flat = flat[np.argsort(-smoothed.ravel()[flat], kind="stable")[:MAX_CANDIDATES]]
    rows, columns = np.unravel_index(flat, shape)
    return low + (np.column_stack([rows, columns]) + 0.5) * CELL


def _significance(anchor: NDArray, direction: NDArray, centre: NDArray) -> tuple[int, float]:
    """Lines concurring at ``centre`` and how far (in standard deviations) above chance."""
    distance = _distance_to_lines(anchor, direction, centre)
    concurring = int(np.count_nonzero(distance <= CONCUR_DISTANCE))
    nearby = int(np.count_nonzero(distance <= BACKGROUND_DISTANCE)) - concurring
    chance = nearby * CONCUR_DISTANCE / (BACKGROUND_DISTANCE - CONCUR_DISTANCE)
    return concurring, (concurring - chance) / math.sqrt(max(chance, 1.0))


def column_centres(
    points: NDArray[np.float64],
    rng: np.random.Generator,
    known: NDArray[np.float64] | None = None,
) -> list[tuple[NDArray[np.float64], int]]:
    """Top-view points where neighbour-pair lines concur far above chance, strongest first.

    Hough peaks (:data:`CELL` grid) are refined to the point the most lines pass within a
    millimetre or two of; a peak is a centre when its concurring lines (within
    :data:`CONCUR_DISTANCE`) number at least :data:`MIN_CONCURRING` and exceed the chance count
    (from the lines passing a little farther) by :data:`MIN_SIGNIFICANCE` standard deviations.
    Lines used by a centre are not counted for the next ones.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        In a frame whose z axis is the lidars' spin axis (upright stations).
    rng : numpy.random.Generator
    known : ndarray, shape (m, 2), optional
        Centres already found: peaks within :data:`MIN_SEPARATION` of them are skipped.

    Returns
    -------
    list of (ndarray shape (2,), int)
        Each centre and its number of concurring lines.
    """
    return search_centres(points, rng, known)[0]


def search_centres(
    points: NDArray[np.float64], rng: np.random.Generator, known: NDArray[np.float64] | None
) -> tuple[list[tuple[NDArray[np.float64], int]], int]:
    """:func:`column_centres` and the number of lines it used."""
    anchor, direction = _pair_lines(points, rng)
    if anchor.shape[0] < 10:
        return [], int(anchor.shape[0])
    refined = [
        _refined_centre(anchor, direction, peak) for peak in _hough_peaks(points, anchor, direction)
    ]
    taken = [] if known is None else [np.asarray(centre) for centre in known]
    remaining = np.ones(anchor.shape[0], dtype=bool)
    centres: list[tuple[NDArray[np.float64], int]] = []
    scores = [_significance(anchor, direction, centre) for centre in refined]
    order = sorted(range(len(refined)), key=lambda number: -scores[number][0])
    for number in order:
        centre = refined[number]
        if any(np.hypot(*(centre - other)) < MIN_SEPARATION for other in taken):
            continue
        support, significance = _significance(anchor[remaining], direction[remaining], centre)
        if support < MIN_CONCURRING or significance < MIN_SIGNIFICANCE:
            continue
        remaining &= _distance_to_lines(anchor, direction, centre) > CONCUR_DISTANCE
        taken.append(centre)
        centres.append((centre, support))
        if len(centres) >= MAX_STATIONS:
            break
    return centres, int(anchor.shape[0])
