"""What a cloud would be, without building it: counts and bounds found a block at a time.

:func:`summarise_array` checks coordinates as :meth:`PointCloud.from_array` does and returns a
:class:`CloudSummary`, keeping only a :class:`FiniteBounds` accumulator (a few kilobytes)
whatever the cloud's size; readers that decode in chunks (LAS/LAZ) feed the accumulator
themselves.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from app.core.blocks import FileRows, coordinate_blocks, share_blocks
from app.core.cloud import (
    MIN_POINTS,
    as_float64,
    check_finite_count,
    check_not_empty,
    checked_attributes,
    checked_coordinates,
    checked_sensor_origin,
    column_extreme,
)

SUMMARY_BLOCK_POINTS = 1 << 16
"""Points per block in :func:`summarise_array`: nothing is written, so a block may fill more
of the L2 cache than a conversion block (figures in docs/performance.md)."""

SUMMARY_ROWS_PER_LINE = 2048
"""Rows folded into one line when :class:`FiniteBounds` reduces a block to its extremes: a
long, vectorised min/max is faster than :func:`column_extreme` on each block (figures in
docs/performance.md)."""


@dataclass(frozen=True)
class CloudSummary:
    """What :meth:`PointCloud.from_array` would make of some coordinates, without the cloud.

    What a service needs to accept an upload (how many points, how many dropped, where they
    lie), found in one pass over the coordinates in the file's own type, a block at a time:
    no float64 copy of the whole cloud is made (:func:`summarise_array`).

    Attributes
    ----------
    n_source : int
        Rows in the source, including non-finite ones.
    n_points : int
        Finite rows: the points the cloud would hold.
    low, high : ndarray, shape (3,), float64
        Axis-aligned bounding box of the finite points (``PointCloud.bounds()``).
    sensor_origin : ndarray, shape (3,) or (k, 3), float64, or None
    n_stations : int or None
        With a ``station_index`` attribute: the number of stations it refers to (its largest
        value + 1), which origins given for the cloud must match.
    """

    n_source: int
    n_points: int
    low: NDArray[np.float64]
    high: NDArray[np.float64]
    sensor_origin: NDArray[np.float64] | None = None
    n_stations: int | None = None

    @property
    def n_dropped(self) -> int:
        """Number of source rows that hold a NaN or infinite coordinate."""
        return self.n_source - self.n_points


def summarise_array(
    points: NDArray,
    attributes: Mapping[str, NDArray] | None = None,
    sensor_origin: NDArray | None = None,
    min_points: int = MIN_POINTS,
    threads: int | None = None,
    file_rows: FileRows | None = None,
) -> CloudSummary:
    """Validate coordinates as :meth:`PointCloud.from_array` does and summarise them.

    The same checks, the same errors and the same counts and bounds as
    ``PointCloud.from_array(...)`` followed by ``bounds()``, but the coordinates are visited
    in cache-sized blocks of their own type: memory stays at one block whatever the cloud's
    size, and for float32 data nothing is widened.

    Parameters
    ----------
    points : array_like, shape (n, 3)
        Coordinates in file order, any numeric dtype, strides and alignment.
    attributes : mapping of str to array_like, each shape (n, ...), optional
        Per-point fields: only their row counts are checked.
    sensor_origin : array_like, shape (3,) or (k, 3), optional
    min_points : int
        Raise :class:`PointCloudError` when fewer finite points remain.
    threads : int, optional
        Threads that share the blocks (as for :meth:`PointCloud.from_array`); default
        :func:`~app.core.blocks.conversion_threads`. The summary does not depend on it.
    file_rows : FileRows, optional
        Where ``points``, a view of a memory-mapped file, lies in that file (read with
        ``pread``, see :class:`~app.core.blocks.FileRows`).

    Returns
    -------
    CloudSummary

    Raises
    ------
    PointCloudError
        Wrong shape, no finite points, fewer than ``min_points`` finite points, attributes
        with the wrong number of rows, a non-finite sensor origin.
    """
    array = checked_coordinates(points)
    n_source = int(array.shape[0])
    if array.dtype.kind not in "iuf":
        array = as_float64(array)
        file_rows = None
    parts = share_blocks(
        n_source,
        threads,
        lambda block_numbers: _summarise_blocks(array, block_numbers, file_rows),
        "summarise_array",
    )
    bounds = parts[0]
    for part in parts[1:]:
        bounds.merge(part)
    return bounds.summary(n_source, min_points, attributes, sensor_origin)


def _summarise_blocks(
    array: NDArray, block_numbers: Iterator[int], file_rows: FileRows | None
) -> FiniteBounds:
    """:class:`FiniteBounds` of the blocks of the numeric (n, 3) ``array`` that
    ``block_numbers`` hands out."""
    bounds = FiniteBounds()
    blocks = coordinate_blocks(array, block_numbers, file_rows, True, SUMMARY_BLOCK_POINTS)
    for _, block in blocks:
        bounds.add(block)
    return bounds


class FiniteBounds:
    """Counts the finite rows of coordinate blocks and bounds them, one block at a time.

    What :func:`summarise_array` (and a reader that decodes in chunks) keeps of a cloud: a
    few kilobytes whatever its size. Each block's whole lines of :data:`SUMMARY_ROWS_PER_LINE`
    rows are reduced to a line of minima and one of maxima in the data's own type: numpy's
    min/max propagate NaN and reach inf, so the two lines also prove the block finite (their
    ``dot`` is finite; it may overflow, see ``app.core.cloud._surely_finite``), without a pass
    of its own. A block with a non-finite value, and a block's last partial line, are checked
    row by row.
    """

    def __init__(self) -> None:
        self.n_finite = 0
        self.low = np.full(3, np.inf)  # of the rows checked row by row
        self.high = np.full(3, -np.inf)
        self.line_low: NDArray | None = None  # running extremes of whole lines, (rows * 3,)
        self.line_high: NDArray | None = None

    def add(self, block: NDArray) -> None:
        """Count and bound the finite rows of a block; the block may be overwritten afterwards.

        Parameters
        ----------
        block : ndarray, shape (k, 3), any real or integer dtype, C-contiguous
        """
        rows = SUMMARY_ROWS_PER_LINE
        check = block.dtype.kind == "f"
        n_whole = len(block) - len(block) % rows
        with np.errstate(invalid="ignore", over="ignore"):
            if n_whole:
                lines = block[:n_whole].reshape(-1, rows * 3)
                block_low = np.minimum.reduce(lines, axis=0)
                block_high = np.maximum.reduce(lines, axis=0)
                if not check or math.isfinite(np.dot(block_low, block_high)):
                    self._add_lines(block_low, block_high)
                    self.n_finite += n_whole
                    block = block[n_whole:]
            if len(block) and check:
                block = block[np.isfinite(block).all(axis=1)]
        if len(block):
            self.n_finite += len(block)
            np.minimum(self.low, column_extreme(block, np.minimum), out=self.low)
            np.maximum(self.high, column_extreme(block, np.maximum), out=self.high)

    def _add_lines(self, line_low: NDArray, line_high: NDArray) -> None:
        if self.line_low is None or self.line_high is None:
            self.line_low, self.line_high = line_low, line_high
        else:
            np.minimum(self.line_low, line_low, out=self.line_low)
            np.maximum(self.line_high, line_high, out=self.line_high)

    def merge(self, other: FiniteBounds) -> None:
        """Add what ``other`` counted and bounded (another thread's blocks).

        Parameters
        ----------
        other : FiniteBounds
        """
        self.n_finite += other.n_finite
        np.minimum(self.low, other.low, out=self.low)
        np.maximum(self.high, other.high, out=self.high)
        if other.line_low is not None and other.line_high is not None:
            self._add_lines(other.line_low, other.line_high)

    def bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The bounding box of every finite row added.

        Returns
        -------
        low, high : ndarray, shape (3,), float64
            inf and -inf when no finite row was added.
        """
        low, high = self.low.copy(), self.high.copy()
        if self.line_low is not None and self.line_high is not None:
            rows = len(self.line_low) // 3  # (rows * 3,) -> (rows, 3) -> (3,)
            np.minimum(low, column_extreme(self.line_low.reshape(rows, 3), np.minimum), out=low)
            np.maximum(high, column_extreme(self.line_high.reshape(rows, 3), np.maximum), out=high)
        return low, high

    def summary(
        self,
        n_source: int,
        min_points: int = MIN_POINTS,
        attributes: Mapping[str, NDArray] | None = None,
        sensor_origin: NDArray | None = None,
    ) -> CloudSummary:
        """The summary of a source whose blocks were all added, after the checks of
        :meth:`PointCloud.from_array` (same errors).

        Parameters
        ----------
        n_source : int
            Rows in the source, including non-finite ones.
        min_points : int
            Raise :class:`PointCloudError` when fewer finite points were added.
        attributes : mapping of str to array_like, each shape (n_source, ...), optional
            Per-point fields: only their row counts are checked.
        sensor_origin : array_like, shape (3,) or (k, 3), optional

        Returns
        -------
        CloudSummary
        """
        check_not_empty(n_source)
        check_finite_count(self.n_finite, n_source, min_points)
        checked = checked_attributes(attributes, n_source)
        low, high = self.bounds()
        station = checked.get("station_index")
        n_stations = int(np.max(station)) + 1 if station is not None and station.size else None
        return CloudSummary(
            n_source, self.n_finite, low, high, checked_sensor_origin(sensor_origin), n_stations
        )
