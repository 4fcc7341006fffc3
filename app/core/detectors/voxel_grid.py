"""The improved detectors' common voxel grid: each point's voxel, one random point per
occupied voxel, and the voxel edge at which a cloud occupies a given number of voxels.

The random choices are :func:`~app.core.detectors.base.point_keys`' (the caller passes them),
so a working set depends on the points and the seed only.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from app.core.cloud import column_extreme
from app.core.threads import for_each_chunk

__all__ = ["VOXEL_BLOCK_ROWS", "auto_voxel_size", "voxel_ids", "voxel_representatives"]


def voxel_representatives(
    points: NDArray[np.float64],
    voxel_size: float,
    origin: NDArray[np.float64],
    keys: NDArray[np.uint64],
) -> NDArray[np.int64]:
    """Indices of one random point per occupied voxel of a grid anchored at ``origin``.

    A random representative (rather than the voxel centroid) keeps the points' noise as it is,
    so the calibration's resampling noise stays that of real points. "Random" is the point
    with the smallest key (:func:`point_keys`) in its voxel.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    voxel_size : float
        Edge length, > 0.
    origin : ndarray, shape (3,)
        Grid corner shared by both clouds (so they are thinned on the same grid).
    keys : ndarray, shape (n,), uint64

    Returns
    -------
    ndarray, shape (k,), int64
        Sorted indices into ``points``.
    """
    voxels, n_cells = voxel_ids(points, voxel_size, origin)
    if n_cells <= _dense_cell_limit(points.shape[0]):
        # per voxel the smallest key, by one unbuffered minimum into a dense array of cells
        # (~10x faster than sorting a million voxel ids); same choice as the sort below
        smallest = np.full(n_cells, np.iinfo(np.uint64).max, dtype=np.uint64)
        np.minimum.at(smallest, voxels, keys)
        holders = np.flatnonzero(keys == smallest[voxels])  # >= 1 per voxel, by index
        _, first = np.unique(voxels[holders], return_index=True)  # ties: the lowest index
        return np.sort(holders[first]).astype(np.int64)
    # per voxel, the point with the smallest key, ties to the lowest index (what a lexsort by
    # voxel then key would pick first), from one sort by voxel and two segment minima: ~3x
    # faster than the lexsort at 1M points
    order = np.argsort(voxels)
    sorted_voxels = voxels[order]
    starts = np.flatnonzero(np.r_[True, sorted_voxels[1:] != sorted_voxels[:-1]])
    sorted_keys = keys[order]
    group_size = np.diff(np.r_[starts, order.size])
    smallest = np.repeat(np.minimum.reduceat(sorted_keys, starts), group_size)
    holders = np.flatnonzero(sorted_keys == smallest)  # >= 1 per voxel, in voxel order
    holder_starts = np.flatnonzero(
        np.r_[True, sorted_voxels[holders[1:]] != sorted_voxels[holders[:-1]]]
    )
    return np.sort(np.minimum.reduceat(order[holders], holder_starts)).astype(np.int64)


VOXEL_BLOCK_ROWS = 1 << 14
"""Rows whose voxel ids :func:`voxel_ids` computes at once (0.38 MiB of float64 coordinates:
under the 1 MiB mmap threshold of ``app.kit.allocator``, so each block reuses the heap's pages
instead of faulting fresh ones in, as 1 << 16 rows' 1.5 MiB did)."""
OCCUPANCY_TASK_ROWS = 8 * VOXEL_BLOCK_ROWS
"""Rows a thread marks per task of :func:`auto_voxel_size`'s counts (~3 ms of CPU: 8 tasks at
1M points; 16k-row tasks cost more hand-overs than they saved, bench/results/perf_1m.md s28)."""


def voxel_ids(
    points: NDArray[np.float64],
    voxel_size: float,
    origin: NDArray[np.float64],
    extremes: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
) -> tuple[NDArray[np.int64], int]:
    """Row-major id of each point's voxel (grid anchored at ``origin``) in the grid that
    bounds the occupied cells, and that grid's size.

    ``extremes``: ``points``' per-axis smallest and largest coordinates (shapes (3,)), when
    the caller has them (not recomputed).

    Returns
    -------
    voxels : ndarray, shape (n,), int64
        In ``0 .. n_cells - 1``.
    n_cells : int
        Cells of the bounding grid (the ids' range; may exceed int64 for absurd extents, in
        which case it is only compared, never allocated).
    """
    low, extent = _voxel_grid(points, voxel_size, origin, extremes)
    voxels = np.empty(points.shape[0], dtype=np.int64)
    for start in range(0, points.shape[0], VOXEL_BLOCK_ROWS):
        rows = slice(start, start + VOXEL_BLOCK_ROWS)
        voxels[rows] = _block_voxel_ids(points[rows], voxel_size, origin, low, extent)
    return voxels, math.prod(int(size) for size in extent)


def _voxel_grid(
    points: NDArray[np.float64],
    voxel_size: float,
    origin: NDArray[np.float64],
    extremes: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The smallest cell (shape (3,)) and the extent in cells (shape (3,)) of the grid that
    bounds ``points``' (n, 3) cells (:func:`voxel_ids`)."""
    # The cell of each axis's smallest (largest) coordinate is the smallest (largest) cell:
    # subtracting, dividing by a positive size and flooring never reverse an order.  So the
    # grid is known first and the ids are computed a block of rows at a time, without the
    # (n, 3) float64 and int64 temporaries (220 MB at 5M points).
    if extremes is None:
        extremes = (column_extreme(points, np.minimum), column_extreme(points, np.maximum))
    low, high = (np.floor((extreme - origin) / voxel_size).astype(np.int64) for extreme in extremes)
    return low, high - low + 1


def _block_voxel_ids(
    block: NDArray[np.float64],
    voxel_size: float,
    origin: NDArray[np.float64],
    low: NDArray[np.int64],
    extent: NDArray[np.int64],
) -> NDArray[np.int64]:
    """:func:`voxel_ids` of a block of rows (shape (b, 3) -> (b,)) in the grid of
    :func:`_voxel_grid`."""
    scaled = block - origin
    scaled /= voxel_size
    cells = np.floor(scaled, out=scaled).astype(np.int64)
    cells -= low
    return (cells[:, 0] * extent[1] + cells[:, 1]) * extent[2] + cells[:, 2]


def _dense_cell_limit(n_points: int) -> int:
    """Largest grid worth a dense per-cell array (8 bytes a cell): a few times the points."""
    return 4 * n_points + (1 << 20)


def _occupied_voxels(
    points: NDArray[np.float64],
    voxel_size: float,
    extremes: tuple[NDArray[np.float64], NDArray[np.float64]],
    threads: int = 1,
) -> int:
    """Voxels of ``voxel_size`` (grid anchored at ``points``' smallest corner) that ``points``
    (n, 3) occupy; ``extremes`` their per-axis smallest and largest coordinates.  A grid of a
    few cells a point is marked by blocks of :data:`OCCUPANCY_TASK_ROWS` rows on up to
    ``threads`` threads (each sets only cells its points occupy: the same count)."""
    lowest = extremes[0]
    low, extent = _voxel_grid(points, voxel_size, lowest, extremes)
    if math.prod(int(size) for size in extent) > _dense_cell_limit(points.shape[0]):
        voxels, _ = voxel_ids(points, voxel_size, lowest, extremes)
        return int(np.unique(voxels).size)
    occupied = np.zeros(math.prod(int(size) for size in extent), dtype=np.bool_)

    def mark(start: int) -> None:
        stop = min(start + OCCUPANCY_TASK_ROWS, points.shape[0])
        for block in range(start, stop, VOXEL_BLOCK_ROWS):
            rows = slice(block, min(block + VOXEL_BLOCK_ROWS, stop))
            # ~10x faster than np.unique's sort at 1M points
            occupied[_block_voxel_ids(points[rows], voxel_size, lowest, low, extent)] = True

    for_each_chunk(mark, range(0, points.shape[0], OCCUPANCY_TASK_ROWS), threads)
    return int(np.count_nonzero(occupied))


def auto_voxel_size(points: NDArray[np.float64], target_count: int, threads: int = 1) -> float:
    """A voxel edge at which ``points`` occupy about ``target_count`` voxels.

    Solved by secant steps on ``log(count)`` versus ``log(size)`` (count ~ size**-2 on
    surfaces), starting from the bounding-box diagonal; a handful of occupancy counts.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    target_count : int
        Desired number of occupied voxels (< n).
    threads : int
        Threads that mark each count's occupied voxels (the same size on any number: the
        detector's keys, beside it, may finish first).

    Returns
    -------
    float
        Voxel edge length.
    """
    extremes = (column_extreme(points, np.minimum), column_extreme(points, np.maximum))
    diagonal = float(np.linalg.norm(extremes[1] - extremes[0]))
    size = diagonal / math.sqrt(target_count)
    count = _occupied_voxels(points, size, extremes, threads)
    slope = -2.0
    for _ in range(6):
        if abs(math.log(count / target_count)) < 0.05:
            break
        new_size = size * math.exp(math.log(target_count / count) / slope)
        new_count = _occupied_voxels(points, new_size, extremes, threads)
        if new_count != count and new_size != size:
            measured = math.log(new_count / count) / math.log(new_size / size)
            slope = min(-0.5, max(-3.0, measured))
        size, count = new_size, new_count
    return size
