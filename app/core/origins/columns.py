"""Where a spinning lidar stood, seen from above: the point its columns radiate from.

An upright spinning lidar fires each column (one azimuth, every ring) in a vertical half-plane
through its axis, and range noise moves a return along its ray, so inside that plane.  Two
returns of one column therefore give, in the top view, a line through the sensor's (x, y)
exactly; two returns of one ring on a level floor lie on a circle round the axis, so the normal
to their pair does too.  Each neighbour pair on a level surface gives both lines, one of which
misses; a Hough vote over all neighbour pairs finds roughly where lines concur, a finer vote
around each peak finds the point most lines pass within millimetres of, and a least-squares fit
on those lines sharpens it.  A cloud merged from several stations has several such points;
random points have none.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

__all__ = [
    "ColumnFit",
    "column_lines",
    "fit_column_centre",
    "horizontal_bounds",
    "normal_z",
]

NEIGHBOURS = 8
"""Neighbour pairs per query point."""
MIN_HORIZONTAL_SHARE = 0.3
"""Pairs whose horizontal part is shorter than this share of their length give no line."""
HORIZONTAL_NORMAL_Z = 0.8
"""Only points whose local surface normal has at least this vertical component give lines."""
CONCUR_SINE = 0.02
"""A line concurs with a centre when it points at it within this sine of an angle."""
HOUGH_CELLS = 100
"""Cells along the longer side of the Hough accumulator."""
HOUGH_LINES = 5_000
"""Lines voting in the Hough accumulator (all of them refine its peak)."""
HOUGH_PEAKS = 6
"""Accumulator peaks refined; the one most lines point at is kept."""
HOUGH_CHUNK_LINES = 400
"""Lines :func:`_hough` draws at once: their (lines, steps) float64 arrays (~0.9 MiB at the
~280 steps of a 100-cell grid) stay under the 1 MiB mmap threshold of ``app.kit.allocator``,
where 4,000 lines' (9 MB each) faulted fresh pages in.  The votes are whole counts, the same
in any chunking."""
REFINE_LINES = 2_000
"""Lines voting on each refinement grid (a random share of those passing near the peak)."""
REFINE_REACH = 1.0
"""The finer vote searches this far (metres) round each peak, or 1.5 Hough cells if farther:
in dense scans (0.2-0.3 degree steps) neighbour pairs are as short as the range noise, and the
lines of the spoilt ones crowd round the lidar in a blob whose peaks lie up to a metre off it."""


@dataclass(frozen=True)
class ColumnFit:
    """The top-view centre of the columns and how clearly the lines concur there.

    Attributes
    ----------
    centre : ndarray, shape (2,)
    concurring_share : float
        Share of the lines pointing at ``centre`` (within :data:`CONCUR_SINE`).
    second_peak_ratio : float
        Votes of the strongest other accumulator peak (1 m away or more) over the chosen one's.
    n_lines : int
    candidates : ndarray, shape (k, 2)
        The refined accumulator peaks, most concurring lines first (``centre`` is the first):
        starts for :func:`~app.core.origins.apex.search_apex` when the lines concur only
        roughly.
    """

    centre: NDArray[np.float64]
    concurring_share: float
    second_peak_ratio: float
    n_lines: int
    candidates: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))


def horizontal_bounds(
    points: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The smallest and largest x and y of ``points`` (n, 3): two arrays of shape (2,).

    Column by column: ``points[:, :2].min(axis=0)`` walks the rows a few values at a time and
    took 70-80 ms at 1M points, this takes 5.
    """
    columns = (points[:, 0], points[:, 1])
    low = np.array([column.min() for column in columns])
    high = np.array([column.max() for column in columns])
    return low, high


def normal_z(neighbourhood: NDArray[np.float64]) -> NDArray[np.float64]:
    """|z| of the unit normal (least-variance direction) of each neighbourhood.

    Closed form, as :func:`numpy.linalg.eigh` of the (n, 3, 3) scatter matrices would give it
    (a fifth of its cost): the smallest eigenvalue from the trigonometric solution of the
    characteristic cubic, its eigenvector the longest cross product of two rows of the scatter
    matrix less that eigenvalue.

    Parameters
    ----------
    neighbourhood : ndarray, shape (n, k, 3)
        Each point's neighbours (itself included).

    Returns
    -------
    ndarray, shape (n,)
        In [0, 1]; 1 for a level (horizontal) neighbourhood.
    """
    centred = neighbourhood - neighbourhood.mean(axis=1, keepdims=True)
    x, y, z = centred[..., 0], centred[..., 1], centred[..., 2]
    xx, yy, zz = (x * x).sum(axis=1), (y * y).sum(axis=1), (z * z).sum(axis=1)
    xy, xz, yz = (x * y).sum(axis=1), (x * z).sum(axis=1), (y * z).sum(axis=1)
    mean = (xx + yy + zz) / 3
    spread = np.sqrt(
        ((xx - mean) ** 2 + (yy - mean) ** 2 + (zz - mean) ** 2) / 6
        + (xy * xy + xz * xz + yz * yz) / 3
    )
    scale = np.where(spread > 0, spread, 1.0)
    a, b, c = (xx - mean) / scale, (yy - mean) / scale, (zz - mean) / scale
    d, e, f = xy / scale, xz / scale, yz / scale
    half_determinant = (a * (b * c - f * f) - d * (d * c - f * e) + e * (d * f - b * e)) / 2
    angle = np.arccos(np.clip(half_determinant, -1.0, 1.0)) / 3
    smallest = mean + 2 * spread * np.cos(angle + 2 * np.pi / 3)
    # rows (xx - s, xy, xz), (xy, yy - s, yz), (xz, yz, zz - s): their cross products
    a, b, c = xx - smallest, yy - smallest, zz - smallest
    crosses = np.stack(
        [
            [xy * yz - xz * b, xz * xy - a * yz, a * b - xy * xy],
            [xy * c - xz * yz, xz * xz - a * c, a * yz - xy * xz],
            [b * c - yz * yz, yz * xz - xy * c, xy * yz - b * xz],
        ]
    )  # (3 products, 3 components, n)
    squared = (crosses**2).sum(axis=1)
    longest = np.argmax(squared, axis=0)
    picked = np.arange(longest.size)
    normal_z = np.abs(crosses[longest, 2, picked])
    return normal_z / np.sqrt(np.maximum(squared[longest, picked], np.finfo(float).tiny))


def column_lines(
    patch: NDArray[np.float64], n_queries: int, rng: np.random.Generator
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Top-view lines through neighbour pairs of ``patch`` (m, 3), and the wall points.

    Returns
    -------
    anchor : ndarray, shape (l, 2)
        A point of each line.
    direction : ndarray, shape (l, 2)
        Unit direction of each line.
    wall_points : ndarray, shape (w, 3)
        Query points on surfaces facing sideways (their elevations show the lidar's rings;
        floors and ceilings would add a false ring at their own height).
    """
    # pykdtree: built and queried in half scipy's time; a missing neighbour (fewer points than
    # NEIGHBOURS + 1) has an index past the end, as scipy gives it
    tree = KDTree(patch)
    queries = rng.choice(len(patch), size=min(n_queries, len(patch)), replace=False)
    _, neighbour = tree.query(patch[queries], k=NEIGHBOURS + 1)
    neighbour = neighbour.astype(np.int64)
    # walls give no column lines (their columns are vertical) but long ridges of ring lines:
    # keep query points on surfaces facing up or down
    upright = normal_z(patch[np.minimum(neighbour, len(patch) - 1)])
    wall_points = patch[queries[upright < 1.0 - HORIZONTAL_NORMAL_Z]]
    horizontal_surface = upright > HORIZONTAL_NORMAL_Z
    queries, neighbour = queries[horizontal_surface], neighbour[horizontal_surface]
    first = np.repeat(queries, NEIGHBOURS)
    second = neighbour[:, 1:].ravel()
    valid = second < len(patch)
    first, second = first[valid], second[valid]
    vector = patch[second] - patch[first]
    horizontal = np.linalg.norm(vector[:, :2], axis=1)
    length = np.linalg.norm(vector, axis=1)
    keep = horizontal > MIN_HORIZONTAL_SHARE * np.maximum(length, 1e-12)
    direction = vector[keep, :2] / horizontal[keep, None]
    # ring pairs on a level floor run along circles round the axis: their normal points at it
    across = np.column_stack([-direction[:, 1], direction[:, 0]])
    anchor = patch[first[keep], :2]
    return np.vstack([anchor, anchor]), np.vstack([direction, across]), wall_points


def _hough(
    anchor: NDArray[np.float64], direction: NDArray[np.float64], low: NDArray, high: NDArray
) -> tuple[list[NDArray[np.float64]], list[float]]:
    """Accumulate lines on a grid over [low, high]; the :data:`HOUGH_PEAKS` best cells at
    least 1 m apart (centres, votes), best first."""
    size = float(np.max(high - low)) / HOUGH_CELLS
    shape = np.ceil((high - low) / size).astype(np.int64) + 1
    reach = float(np.linalg.norm(high - low))
    steps = np.arange(-reach, reach, size)
    grid = np.zeros(int(shape[0] * shape[1]), dtype=np.float64)
    for start in range(0, len(anchor), HOUGH_CHUNK_LINES):
        a = anchor[start : start + HOUGH_CHUNK_LINES]
        d = direction[start : start + HOUGH_CHUNK_LINES]
        # x and y apart: tests along the last axis of (lines, steps, 2) arrays took 3x longer
        x = a[:, 0, None] + steps[None, :] * d[:, 0, None]
        y = a[:, 1, None] + steps[None, :] * d[:, 1, None]
        cell_x = ((x - low[0]) / size).astype(np.int64)
        cell_y = ((y - low[1]) / size).astype(np.int64)
        inside = (x >= low[0]) & (y >= low[1]) & (cell_x < shape[0]) & (cell_y < shape[1])
        grid += np.bincount(cell_x[inside] * shape[1] + cell_y[inside], minlength=grid.size)
    votes = grid.reshape(shape)
    smooth = votes.copy()
    smooth[1:, :] += votes[:-1, :]
    smooth[:-1, :] += votes[1:, :]
    smooth[:, 1:] += votes[:, :-1]
    smooth[:, :-1] += votes[:, 1:]
    rows, cols = np.indices(shape)
    centres, peaks = [], []
    for _ in range(HOUGH_PEAKS):
        best = np.unravel_index(int(np.argmax(smooth)), shape)
        if smooth[best] <= 0:
            break
        centres.append(low + (np.array(best) + 0.5) * size)
        peaks.append(float(smooth[best]))
        smooth[np.hypot((rows - best[0]) * size, (cols - best[1]) * size) < 1.0] = 0.0
    return centres, peaks


def _densest_concurrence(
    normal: NDArray, constant: NDArray, centre: NDArray, reach: float
) -> NDArray[np.float64]:
    """The point within ``reach`` of ``centre`` that the most lines pass close to, on finer and
    finer grids.

    A vote, not a fit: lines that miss the lidar (ring pairs spoilt by range noise, many when
    the scan is dense and neighbours are close) do not pull it as they pull a least squares
    started a Hough cell away.  Lines are ``normal @ x == constant`` (unit normals (l, 2),
    constants (l,)), in random order.
    """
    stages = ((reach, 0.05, 0.03), (0.05, 0.01, 0.01), (0.012, 0.003, 0.004))
    for half_width, step, band in stages:
        miss = np.abs(normal @ centre - constant)
        near = np.flatnonzero(miss <= half_width * np.sqrt(2.0) + band)[:REFINE_LINES]
        if len(near) < 10:
            break
        offsets = np.arange(-half_width, half_width + step / 2, step)
        votes = _grid_votes(normal[near], constant[near], centre, offsets, band)
        first, second = np.unravel_index(int(np.argmax(votes)), votes.shape)
        centre = centre + np.array([offsets[first], offsets[second]])
    return centre


def _grid_votes(
    normal: NDArray, constant: NDArray, centre: NDArray, offsets: NDArray, band: float
) -> NDArray[np.int64]:
    """How many lines pass within ``band`` of each point ``centre + (offsets[i], offsets[j])``,
    shape (k, k).

    For a line and a row ``i`` the points it passes close to are a run of ``j``: a run per line
    and row (a difference array summed along ``j``) instead of a distance per line and point.
    Lines are ``normal @ x == constant`` (unit normals (l, 2), constants (l,)); ``offsets``
    (k,) are evenly spaced.
    """
    count = len(offsets)
    step = float(offsets[1] - offsets[0]) if count > 1 else 1.0
    # line value at row i, column 0: a_i; along a row it changes by normal_y * step per column
    row_value = (
        normal[:, :1] * (centre[0] + offsets[None, :])
        + normal[:, 1:] * (centre[1] + offsets[0])
        - constant[:, None]
    )  # (lines, k)
    slope = normal[:, 1:] * step  # (lines, 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        low_bound = (-band - row_value) / slope
        high_bound = (band - row_value) / slope
    first = np.ceil(np.minimum(low_bound, high_bound) - 1e-9)
    last = np.floor(np.maximum(low_bound, high_bound) + 1e-9)
    flat = np.abs(slope[:, 0]) < 1e-12  # a line along the rows: every column or none
    first[flat] = np.where(np.abs(row_value[flat]) <= band, 0, count)
    last[flat] = count - 1
    first = np.clip(first, 0, count).astype(np.int64)
    last = np.clip(last, -1, count - 1).astype(np.int64)
    keep = first <= last
    # each run as +1 at its first column and -1 after its last, rows of count + 1 cells
    row_start = np.broadcast_to(np.arange(count) * (count + 1), first.shape)[keep]
    size = count * (count + 1)
    difference = np.bincount(row_start + first[keep], minlength=size) - np.bincount(
        row_start + last[keep] + 1, minlength=size
    )
    return np.cumsum(difference.reshape(count, count + 1)[:, :count], axis=1)


def _refine(
    normal: NDArray, constant: NDArray, centre: NDArray, reach: float
) -> NDArray[np.float64]:
    """The densest concurrence within ``reach`` (m) of ``centre``, then the least-squares point
    of the lines passing within a shrinking distance of it.

    Lines are ``normal @ x == constant`` (unit normals (l, 2), constants (l,)).
    """
    centre = _densest_concurrence(normal, constant, np.asarray(centre, dtype=np.float64), reach)
    for tolerance in (0.03, 0.01):
        near = np.abs(normal @ centre - constant) < tolerance
        if np.count_nonzero(near) < 10:
            break
        n = normal[near]
        matrix = n.T @ n
        if np.linalg.cond(matrix) > 1e8:
            break
        centre = np.linalg.solve(matrix, n.T @ constant[near])
    return centre


def concurring_share(normal: NDArray, constant: NDArray, anchor: NDArray, centre: NDArray) -> float:
    """Share of the lines ``normal @ x == constant`` through ``anchor`` (l, 2) pointing at
    ``centre`` within :data:`CONCUR_SINE`."""
    cross = np.abs(normal @ centre - constant)
    distance = np.hypot(anchor[:, 0] - centre[0], anchor[:, 1] - centre[1])
    pointing = np.count_nonzero(cross < CONCUR_SINE * np.maximum(distance, 1e-9))
    return float(pointing) / len(anchor) if len(anchor) else 0.0


def fit_column_centre(
    anchor: NDArray[np.float64], direction: NDArray[np.float64], low: NDArray, high: NDArray
) -> ColumnFit:
    """The top-view point where the column lines concur, inside the box [low, high] (2,).

    The Hough accumulator's best few peaks are refined; the one most lines point at wins.
    """
    if len(anchor) < 20:
        return ColumnFit(np.asarray((low + high) / 2.0), 0.0, 1.0, len(anchor))
    shuffled = np.random.default_rng(0).permutation(len(anchor))
    voters = shuffled[:HOUGH_LINES]
    centres, peaks = _hough(anchor[voters], direction[voters], low, high)
    reach = max(1.5 * float(np.max(high - low)) / HOUGH_CELLS, REFINE_REACH)
    anchor, direction = anchor[shuffled], direction[shuffled]  # the refinements sample lines
    normal = np.column_stack([-direction[:, 1], direction[:, 0]])
    constant = np.einsum("ij,ij->i", normal, anchor)
    refined = [_refine(normal, constant, centre, reach) for centre in centres]
    shares = [concurring_share(normal, constant, anchor, centre) for centre in refined]
    best = int(np.argmax(shares))
    others = [peak for index, peak in enumerate(peaks) if index != best]
    order = sorted(range(len(refined)), key=lambda index: (index != best, -shares[index]))
    return ColumnFit(
        centre=refined[best],
        concurring_share=shares[best],
        second_peak_ratio=max(others, default=0.0) / peaks[best] if peaks[best] > 0 else 1.0,
        n_lines=len(anchor),
        candidates=np.array([refined[index] for index in order]).reshape(-1, 2),
    )
