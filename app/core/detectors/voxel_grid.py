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


def voxel_ids(
    points: NDArray[np.float64], voxel_size: float, origin: NDArray[np.float64]
) -> tuple[NDArray[np.int64], int]:
    """Row-major id of each point's voxel (grid anchored at ``origin``) in the grid that
    bounds the occupied cells, and that grid's size.

    Returns
    -------
    voxels : ndarray, shape (n,), int64
        In ``0 .. n_cells - 1``.
    n_cells : int
        Cells of the bounding grid (the ids' range; may exceed int64 for absurd extents, in
        which case it is only compared, never allocated).
    """
    # The cell of each axis's smallest (largest) coordinate is the smallest (largest) cell:
    # subtracting, dividing by a positive size and flooring never reverse an order.  So the
    # grid is known first and the ids are computed a block of rows at a time, without the
    # (n, 3) float64 and int64 temporaries (220 MB at 5M points).
    low, high = (
        np.floor((column_extreme(points, ufunc) - origin) / voxel_size).astype(np.int64)
        for ufunc in (np.minimum, np.maximum)
    )
    extent = high - low + 1
    voxels = np.empty(points.shape[0], dtype=np.int64)
    for start in range(0, points.shape[0], VOXEL_BLOCK_ROWS):
        rows = slice(start, start + VOXEL_BLOCK_ROWS)
        scaled = points[rows] - origin
        scaled /= voxel_size
        cells = np.floor(scaled, out=scaled).astype(np.int64)
        cells -= low
        voxels[rows] = (cells[:, 0] * extent[1] + cells[:, 1]) * extent[2] + cells[:, 2]
    return voxels, math.prod(int(size) for size in extent)


def _dense_cell_limit(n_points: int) -> int:
    """Largest grid worth a dense per-cell array (8 bytes a cell): a few times the points."""
    return 4 * n_points + (1 << 20)


def _occupied_voxels(points: NDArray[np.float64], voxel_size: float) -> int:
    voxels, n_cells = voxel_ids(points, voxel_size, column_extreme(points, np.minimum))
    if n_cells <= _dense_cell_limit(points.shape[0]):
        occupied = np.zeros(n_cells, dtype=np.bool_)
        occupied[voxels] = True  # ~10x faster than np.unique's sort at 1M points
        return int(np.count_nonzero(occupied))
    return int(np.unique(voxels).size)


def auto_voxel_size(points: NDArray[np.float64], target_count: int) -> float:
    """A voxel edge at which ``points`` occupy about ``target_count`` voxels.

    Solved by secant steps on ``log(count)`` versus ``log(size)`` (count ~ size**-2 on
    surfaces), starting from the bounding-box diagonal; a handful of ``np.unique`` calls.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    target_count : int
        Desired number of occupied voxels (< n).

    Returns
    -------
    float
        Voxel edge length.
    """
    diagonal = float(
        np.linalg.norm(column_extreme(points, np.maximum) - column_extreme(points, np.minimum))
    )
    size = diagonal / math.sqrt(target_count)
    count = _occupied_voxels(points, size)
    slope = -2.0
    for _ in range(6):
        if abs(math.log(count / target_count)) < 0.05:
            break
        new_size = size * math.exp(math.log(target_count / count) / slope)
        new_count = _occupied_voxels(points, new_size)
        if new_count != count and new_size != size:
            measured = math.log(new_count / count) / math.log(new_size / size)
            slope = min(-0.5, max(-3.0, measured))
        size, count = new_size, new_count
    return size
