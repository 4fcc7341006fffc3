"""Points where the top-view lines of neighbour pairs concur: the (x, y) of lidar stations.

An upright spinning lidar fires each column in a vertical half-plane through its axis, and
range noise moves a return along its ray: two neighbouring returns of one column lie, in the
top view, on a line through the station's (x, y) exactly.  Used by
:mod:`app.core.origins.station_recovery`.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.origins.columns import _grid_votes, horizontal_bounds, normal_z

__all__ = ["MAX_STATIONS", "column_centres", "search_centres"]

PAIR_NEIGHBOURS = 4
MAX_PAIR_LENGTH = 0.5
MIN_HORIZONTAL_SHARE = 0.3
"""A pair whose top-view part is shorter than this share of its length gives no line."""
MAX_LINES = 30_000
PAIR_QUERIES = 24_000
"""Points (a seeded random share) whose neighbour pairs are made into lines: 24k give 1.5-2.5
usable pairs each, more than :data:`MAX_LINES` (40k found the same centres, within 0.3 mm, at
half again the cost of the neighbour queries and normals)."""
FULL_SEARCH_POINTS = 100_000
"""Clouds of this many points or more are searched with all of :data:`MAX_LINES` and
:data:`PAIR_QUERIES` (a first pass on a subset of :mod:`app.core.origins.station_recovery`, 200k
points, is searched as before); fewer points get proportionally fewer: the residual of a later
pass holds a few stations' returns, their pairs at least as dense as in the first pass.  (The
first pass scaled too, at 0.9 of its lines, changed the stations enough to drop the IoU of a
bench scene from 0.91 to 0.86.)"""
MIN_LINES = 4_000
"""Nor fewer than this many lines (and the queries for them) in a small cloud."""
VOTE_REACH = 10.0
"""Each line votes within this many metres of its pair (a lidar's dense returns are near it)."""
MIN_VOTE_DISTANCE = 0.3
"""Nor nearer than this: every line passes through its own pair, so dense patches of returns
(a lidar's first rings on the floor) would otherwise outvote the stations."""
CELL = 0.02
"""Hough cell (metres): fine, so that the few lines of a station hidden among others' still
stand out of the lines that pass by chance."""
VOTE_STRIDE = 2
"""A line votes every this many cells along it (every cell of a 3 x 3 peak window gets a vote
or two from a line through its middle): half the votes of one a cell, the same stations."""
VOTE_BATCH = 4_000_000
"""Votes counted into the grid at once (each count adds a whole grid)."""
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
NEAR_PEAK = 0.2
"""A peak is refined and tested on the lines passing within this many metres of it: the
refinement moves it by less than 8 cm, and the tests count lines within
:data:`BACKGROUND_DISTANCE` of where it ends."""
QUERY_CELL = 0.5
"""Neighbour queries are made cell by cell of this edge (metres)."""
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
    share = min(1.0, max(points.shape[0] / FULL_SEARCH_POINTS, MIN_LINES / MAX_LINES))
    max_lines, queries = round(MAX_LINES * share), round(PAIR_QUERIES * share)
    if points.shape[0] > queries:  # enough lines from a seeded share of the points
        points = points[np.sort(rng.choice(points.shape[0], queries, replace=False))]
    distance, index = _query_in_space_order(tree, points, max(PAIR_NEIGHBOURS + 1, 8))
    neighbourhood = np.take(tree_points, index, axis=0)  # (a third of indexing's cost)
    level = normal_z(neighbourhood) >= MIN_NORMAL_Z
    offset = neighbourhood[:, 1 : PAIR_NEIGHBOURS + 1] - points[:, None, :]  # (n, k, 3)
    length = distance[:, 1 : PAIR_NEIGHBOURS + 1]
    horizontal = np.hypot(offset[..., 0], offset[..., 1])
    usable = (
        level[:, None]
        & (length > 0)
        & (length <= MAX_PAIR_LENGTH)
        & (horizontal >= MIN_HORIZONTAL_SHARE * length)
    )
    rows, columns = np.nonzero(usable)
    if rows.size > max_lines:
        pick = np.sort(rng.choice(rows.size, max_lines, replace=False))
        rows, columns = rows[pick], columns[pick]
    anchor = points[rows, :2]
    direction = offset[rows, columns, :2] / horizontal[rows, columns, None]
    order = rng.permutation(rows.size)  # refinements take the first lines near a peak
    return anchor[order], direction[order]


def _query_in_space_order(
    tree: KDTree, points: NDArray[np.float64], k: int
) -> tuple[NDArray[np.float64], NDArray[np.uint32]]:
    """``tree.query(points, k=k)``, the queries made in order of :data:`QUERY_CELL` cells.

    Queries in the cloud's (shuffled) order jump across the tree; sorted by cell they reuse
    what the previous one loaded (40k queries at 1M points: 0.14 -> 0.08 s).  Same results,
    in the order of ``points``.
    """
    cell = np.floor((points - points.min(axis=0)) / QUERY_CELL).astype(np.int64)
    span = cell.max(axis=0) + 1
    order = np.argsort((cell[:, 0] * span[1] + cell[:, 1]) * span[2] + cell[:, 2], kind="stable")
    sorted_distance, sorted_index = tree.query(points[order], k=k)
    distance = np.empty_like(sorted_distance)
    index = np.empty_like(sorted_index)
    distance[order] = sorted_distance
    index[order] = sorted_index
    return distance, index


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
        # lines as normal . x == constant; votes per grid point as runs of columns per row
        normal = np.column_stack([direction[near, 1], -direction[near, 0]])
        constant = np.einsum("ld,ld->l", normal, anchor[near])
        votes = _grid_votes(normal, constant, centre, offsets, band)
        first, second = np.unravel_index(int(np.argmax(votes)), votes.shape)
        centre = centre + np.array([offsets[first], offsets[second]])
    close = _distance_to_lines(anchor, direction, centre) <= CONCUR_DISTANCE
    if close.sum() >= 2:
        centre = _least_squares_point(anchor[close], direction[close])
    return centre


def _hough_peaks(
    points: NDArray[np.float64], anchor: NDArray, direction: NDArray
) -> NDArray[np.float64]:
    """Top-view cells where many lines cross, strongest first, shape (c, 2)."""
    low, high = horizontal_bounds(points)
    low = low - 1.0
    shape = np.ceil((high + 1.0 - low) / CELL).astype(np.int64) + 1
    votes = _hough_votes(((anchor - low) / CELL).astype(np.float32), direction, shape)
    from scipy.ndimage import uniform_filter  # on first use: API processes need no scipy

    smoothed = uniform_filter(votes.reshape(shape), size=3, mode="constant")
    flat = _strongest_peaks(smoothed, PEAK_SEPARATION, MAX_CANDIDATES)
    rows, columns = np.unravel_index(flat, shape)
    return low + (np.column_stack([rows, columns]) + 0.5) * CELL


def _vote_steps() -> NDArray[np.float32]:
    """Distances (cells) along a line at which it votes, ascending, shape (s,)."""
    steps = np.arange(MIN_VOTE_DISTANCE / CELL, VOTE_REACH / CELL, VOTE_STRIDE, dtype=np.float32)
    return np.concatenate([-steps[::-1], steps])


def _hough_votes(
    start_cell: NDArray[np.float32], direction: NDArray[np.float64], shape: NDArray[np.int64]
) -> NDArray[np.float64]:
    """Votes of the lines per cell of a grid, flat, shape (shape[0] * shape[1],).

    Line ``i`` votes for the cell of ``start_cell[i] + step * direction[i]`` (in cell units,
    single precision: the vote is the costly part of a search) at each of :func:`_vote_steps`
    that falls inside the grid.  Lines are voted a block at a time into reused buffers, in
    place (a third faster than a new array per operation).
    """
    steps = _vote_steps()
    direction32 = direction.astype(np.float32)
    size = int(shape[0] * shape[1])
    index_type = np.int32 if size < 2**31 else np.int64
    # float32 holds the grid's edges exactly (a grid of fewer than 2**24 cells a side)
    rows, columns = np.float32(shape[0]), np.float32(shape[1])
    votes = np.zeros(size, dtype=np.int64)
    block = 1024
    row = np.empty((block, steps.size), dtype=np.float32)
    column = np.empty_like(row)
    test = np.empty(row.shape, dtype=bool)
    batch: list[NDArray] = []  # cells voted for, counted a few million at a time
    pending = 0
    for start in range(0, start_cell.shape[0], block):
        part = slice(start, start + block)
        count = min(block, start_cell.shape[0] - start)
        line_row, line_column, line_test = row[:count], column[:count], test[:count]
        np.multiply(steps, direction32[part, 0, None], out=line_row)
        line_row += start_cell[part, 0, None]
        np.multiply(steps, direction32[part, 1, None], out=line_column)
        line_column += start_cell[part, 1, None]
        inside = line_row >= 0
        inside &= np.less(line_row, rows, out=line_test)
        inside &= np.greater_equal(line_column, 0, out=line_test)
        inside &= np.less(line_column, columns, out=line_test)
        cells = line_row[inside].astype(index_type)
        cells *= index_type(shape[1])
        cells += line_column[inside].astype(index_type)
        batch.append(cells)
        pending += cells.size
        if pending >= VOTE_BATCH or start + block >= start_cell.shape[0]:
            votes += np.bincount(np.concatenate(batch), minlength=size)
            batch, pending = [], 0
    return votes.astype(np.float64)


def _strongest_peaks(grid: NDArray[np.float64], separation: int, count: int) -> NDArray[np.int64]:
    """Flat indices of the ``count`` largest positive local maxima of ``grid`` (r, c), largest
    first (ties: lower index first).

    A local maximum is at least every value in the ``separation`` square round it (zero beyond
    the edges), as ``grid == maximum_filter(grid, separation, mode="constant")``; only the
    largest cells are tested (more while too few of them are maxima), not the whole grid: first
    64 a maximum wanted, which on the station searches' votes is enough at once (each further
    round partitions the whole grid again).
    """
    values = grid.ravel()
    half = separation // 2
    offsets = np.arange(-half, separation - half)
    tested = 0
    while True:
        tested = min(values.size, max(64 * count, 4 * tested, 512))
        threshold = np.partition(values, values.size - tested)[values.size - tested]
        cells = np.flatnonzero((values >= threshold) & (values > 0))
        rows, columns = np.divmod(cells, grid.shape[1])
        around_rows = rows[:, None, None] + offsets[None, :, None]
        around_columns = columns[:, None, None] + offsets[None, None, :]
        inside = (
            (around_rows >= 0)
            & (around_rows < grid.shape[0])
            & (around_columns >= 0)
            & (around_columns < grid.shape[1])
        )
        around = np.where(
            inside,
            values[
                np.clip(around_rows, 0, grid.shape[0] - 1) * grid.shape[1]
                + np.clip(around_columns, 0, grid.shape[1] - 1)
            ],
            0.0,
        )
        peaks = cells[
            values[cells] >= around.reshape(cells.size, separation**2).max(axis=1, initial=0.0)
        ]
        # every maximum above the threshold is among the tested cells: enough of them, or all
        if peaks.size >= count or tested == values.size or threshold <= 0:
            return peaks[np.argsort(-values[peaks], kind="stable")[:count]]


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
    """:func:`column_centres` and the number of lines it used.

    Each peak is refined and tested on the lines passing within :data:`NEAR_PEAK` of it (one
    matrix product for all peaks): every line that the refinement and the tests count at the
    refined point is among them (the full set is used when a refinement moves farther), so the
    centres are those of testing every line, at a tenth of the cost.
    """
    anchor, direction = _pair_lines(points, rng)
    if anchor.shape[0] < 10:
        return [], int(anchor.shape[0])
    peaks = _hough_peaks(points, anchor, direction)
    everything = np.arange(anchor.shape[0])
    near_sets = []
    refined = []
    # distance of each peak to each line as one product: |p x d - a x d|, shape (c, l)
    cross = anchor[:, 0] * direction[:, 1] - anchor[:, 1] * direction[:, 0]
    for start in range(0, peaks.shape[0], 16):
        part = peaks[start : start + 16]
        distance = np.abs(
            np.outer(part[:, 0], direction[:, 1]) - np.outer(part[:, 1], direction[:, 0]) - cross
        )
        for peak, row in zip(part, distance, strict=True):
            near = np.flatnonzero(row <= NEAR_PEAK)
            centre = _refined_centre(anchor[near], direction[near], peak)
            if np.hypot(*(centre - peak)) > NEAR_PEAK - BACKGROUND_DISTANCE - 1e-3:
                near = everything  # moved out of reach: refined again on every line
                centre = _refined_centre(anchor, direction, peak)
            near_sets.append(near)
            refined.append(centre)
    taken = [] if known is None else [np.asarray(centre) for centre in known]
    remaining = np.ones(anchor.shape[0], dtype=bool)
    centres: list[tuple[NDArray[np.float64], int]] = []
    scores = [
        _significance(anchor[near], direction[near], centre)
        for near, centre in zip(near_sets, refined, strict=True)
    ]
    order = sorted(range(len(refined)), key=lambda number: -scores[number][0])
    for number in order:
        centre = refined[number]
        if any(np.hypot(*(centre - other)) < MIN_SEPARATION for other in taken):
            continue
        near = near_sets[number][remaining[near_sets[number]]]
        support, significance = _significance(anchor[near], direction[near], centre)
        if support < MIN_CONCURRING or significance < MIN_SIGNIFICANCE:
            continue
        near = near_sets[number]
        remaining[
            near[_distance_to_lines(anchor[near], direction[near], centre) <= CONCUR_DISTANCE]
        ] = False
        taken.append(centre)
        centres.append((centre, support))
        if len(centres) >= MAX_STATIONS:
            break
    return centres, int(anchor.shape[0])
