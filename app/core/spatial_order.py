"""A spatial (Z-order) permutation of a cloud, to visit it a cache-friendly chunk at a time.

KD-tree queries and neighbourhood gathers over a cloud in file order jump across the whole
cloud from one point to the next (synthetic pairs and many merged scans are shuffled), so
every query walks a cold part of the tree.  Visiting the points along a Morton (Z-order) curve
keeps consecutive queries next to each other: on a 1M-point warehouse pair the k-NN query of a
cloud against itself takes about a quarter of the time, with the same results (each point's
answer does not depend on the order it is asked in).  Figures in ``docs/performance.md``.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
from numpy.typing import NDArray

from app.core.cloud import column_extreme

__all__ = ["MORTON_BITS", "ordered_chunks", "spatial_order"]

MORTON_BITS = 16
"""Bits a coordinate of the Morton code: 65,536 cells along the longest side of the bounding
box (1.5 mm on a 100 m site), far finer than any cache-sized chunk."""
_SPREAD_STEPS = (
    (16, 0x0000FF0000FF),
    (8, 0x00F00F00F00F),
    (4, 0x0C30C30C30C3),
    (2, 0x249249249249),
)
"""Shifts and masks that move bit ``i`` of a 16-bit value to bit ``3 i``."""
ORDER_CHUNK = 1 << 14
"""Points per chunk of :func:`spatial_order`: its (chunk, 3) temporaries (0.38 MiB) stay under
the 1 MiB mmap threshold (``app.core.localise.settings``' note), so the heap's pages are reused
chunk after chunk; at 1 << 16 (1.5 MiB) they faulted ~19k fresh pages in at 1M + 1M points."""


def _spread_bits(values: NDArray[np.uint64]) -> NDArray[np.uint64]:
    """Bit ``i`` of each 16-bit value moved to bit ``3 i`` (in place), shape kept."""
    for shift, mask in _SPREAD_STEPS:
        values |= values << np.uint64(shift)
        values &= np.uint64(mask)
    return values


def spatial_order(points: NDArray[np.floating]) -> NDArray[np.intp]:
    """The permutation that sorts ``points`` along a Morton (Z-order) curve.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        Finite coordinates (float32 or float64; any frame).

    Returns
    -------
    ndarray, shape (n,), intp
        ``points[order]`` visits the cloud cell by cell of a 2^16 grid over its bounding
        cube, in Z-order.  Points of one cell come in an unspecified order: callers use the
        permutation only to choose which rows to process together, never for a result that
        depends on it.
    """
    n = points.shape[0]
    if n == 0:
        return np.empty(0, dtype=np.intp)
    low = column_extreme(points, np.minimum).astype(np.float64)
    extent = float((column_extreme(points, np.maximum) - low).max())
    scale = ((1 << MORTON_BITS) - 1) / extent if extent > 0 else 0.0
    code = np.empty(n, dtype=np.uint64)
    for start in range(0, n, ORDER_CHUNK):
        chunk = points[start : start + ORDER_CHUNK]
        cells = ((chunk - low) * scale).astype(np.uint64)
        np.clip(cells, 0, (1 << MORTON_BITS) - 1, out=cells)
        block = _spread_bits(np.ascontiguousarray(cells[:, 0]))
        block |= _spread_bits(np.ascontiguousarray(cells[:, 1])) << np.uint64(1)
        block |= _spread_bits(np.ascontiguousarray(cells[:, 2])) << np.uint64(2)
        code[start : start + ORDER_CHUNK] = block
    return np.argsort(code)


def ordered_chunks(order: NDArray[np.intp] | None, n: int, size: int) -> Iterator[NDArray | slice]:
    """Row selections of ``size`` points that together cover ``0..n - 1`` once.

    Parameters
    ----------
    order : ndarray, shape (n,), or None
        A permutation (:func:`spatial_order`): chunks are its consecutive runs; None: slices
        in file order.
    n : int
    size : int

    Yields
    ------
    ndarray of intp, shape (<= size,), or slice
        Rows to read (``values[rows]``) and to write back (``out[rows] = ...``).
    """
    for start in range(0, n, size):
        yield slice(start, start + size) if order is None else order[start : start + size]
