"""The point cloud container used throughout the core.

A :class:`PointCloud` holds finite float64 coordinates together with the bookkeeping needed to
map per-point results back to the rows of the file it was read from (points with NaN/inf
coordinates are dropped on load but keep their place in exported labels).

Georeferenced data (e.g. UTM coordinates, x ~ 5e5, y ~ 5e6) loses precision in float32 and in
covariance sums; :func:`choose_local_origin` gives a rounded origin that callers subtract before
numeric work and add back when reporting coordinates.
"""

from __future__ import annotations

import itertools
import math
import os
import threading
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from app.core.errors import PointCloudError
from app.core.threads import available_threads, configured_threads, usable_cpus

MIN_POINTS = 10
"""Fewest finite points a cloud may have: below this no detector or registration is meaningful."""


CHECK_BLOCK_POINTS = 1 << 15
"""Points converted per block in :meth:`PointCloud.from_array`: a block's input and float64
output (1.2 MB for float32 x, y, z) stay in the L2 cache while its finiteness is checked."""

PARALLEL_MIN_POINTS = 1 << 18
"""Fewest rows per thread when :meth:`PointCloud.from_array` converts with several threads
(starting a thread costs ~50 us, converting 256k float32 rows ~0.4 ms)."""

MAX_CONVERSION_THREADS = 2
"""Most threads :func:`conversion_threads` suggests."""

SUMMARY_BLOCK_POINTS = 1 << 16
"""Points per block in :func:`summarise_array`: nothing is written, so a block may fill more
of the L2 cache than a conversion block. 1M-point binary PLY, 40 interleaved rounds, best
(median): one thread 1.39 (1.55) ms, two 1.29 (1.42) ms; with 32k-point blocks 1.43 (1.62)
and 1.36 (1.60) ms; 128k-point blocks no better than 64k. numpy's min/max reductions hold
the GIL, so a second thread only overlaps the ``pread`` copies."""

SUMMARY_ROWS_PER_LINE = 2048
"""Rows folded into one line when :class:`FiniteBounds` reduces a block to its extremes
(a long, vectorised min/max over (16, 6144) float32 per default block: 5 us where
:func:`column_extreme` took 16 us)."""


@dataclass(frozen=True)
class FileRows:
    """Where a memory-mapped (n, 3) coordinate view lies in its file, to read it with ``pread``.

    Converting straight from a file's memory map pays a page-table walk and a first-touch
    fault on every page; reading each block with ``os.preadv`` into a cache-sized buffer and
    widening it there is faster (1M float32 points, best of 60 alternating reads: one thread
    5.07-5.32 ms against 5.68-6.31 ms, two threads 3.86-3.99 ms against 4.20-4.27 ms).

    Attributes
    ----------
    file_descriptor : int
        An open descriptor of the file (positional reads: threads may share it).
    offset : int
        Byte offset of the first row's first coordinate.
    """

    file_descriptor: int
    offset: int


class _SourceIndex:
    """``PointCloud.source_index``: stored ``None`` (no row dropped) becomes an ``arange`` on first
    access, so loading a cloud without NaN rows does not write 8 bytes per point up front."""

    def __set_name__(self, owner: type, name: str) -> None:
        self._slot = f"_{name}"

    def __get__(self, instance: object, owner: type | None = None) -> NDArray[np.int64]:
        if instance is None:
            raise AttributeError(self._slot[1:])  # no class-level default: the field is required
        stored = instance.__dict__[self._slot]
        if stored is None:
            stored = np.arange(instance.n_source, dtype=np.int64)  # type: ignore[attr-defined]
            instance.__dict__[self._slot] = stored
        return stored

    def __set__(self, instance: object, value: NDArray[np.int64] | None) -> None:
        instance.__dict__[self._slot] = value


def _is_owned_float64(array: NDArray) -> bool:
    """Native float64, C-contiguous and writeable: usable as the cloud's points without a copy."""
    return (
        array.dtype == np.float64
        and array.dtype.isnative
        and array.flags.c_contiguous
        and array.flags.writeable
    )


def _surely_finite(values: NDArray) -> bool:
    """True only when every value of the float array ``values`` is finite (one pass, no temporary).

    ``dot(v, v)`` is NaN or inf as soon as one value is; it may also overflow to inf for huge
    finite values (|v| > ~1e154 in float64), so False means "check row by row", never "not
    finite".
    """
    flat = values.reshape(-1)
    if flat.dtype.kind != "f" or not flat.dtype.isnative or not flat.flags.c_contiguous:
        return bool(np.isfinite(values).all())
    with np.errstate(over="ignore", invalid="ignore"):
        return bool(np.isfinite(np.dot(flat, flat)))


def conversion_threads() -> int:
    """Threads :meth:`PointCloud.from_array` widens large inputs with by default.

    ``OMP_NUM_THREADS`` when set (the thread budget the service and the benchmarks give a
    process), at most :data:`MAX_CONVERSION_THREADS`. Otherwise the caller's thread plus one
    per CPU (of those this process may run on) that the machine's 1-minute load average
    leaves idle, like ``make -l``: a helper only pays when it gets a core of its own. On an
    oversubscribed machine a helper preempted while it holds the GIL stalls the caller for a
    whole time slice. Measured on 2 CPUs, 1M-point binary PLY read: at load ~2 one thread
    2.4 ms, two 1.8 ms; at load 2.8 two threads ~7 % slower in the median; at load 4.4 two
    threads with the rows split in halves up front 7.5 ms against 2.6 ms. The rule errs
    towards one thread: the loss when oversubscribed is larger than the gain when not.
    """
    if configured_threads() is not None:
        return min(available_threads(), MAX_CONVERSION_THREADS)
    usable = usable_cpus()
    try:
        load = os.getloadavg()[0]
    except (AttributeError, OSError):  # no load average (Windows)
        load = 0.0
    idle_cpus = int(usable - load + 0.5)
    return max(1, min(1 + idle_cpus, usable, MAX_CONVERSION_THREADS))


def _float64_checked(
    array: NDArray, threads: int = 1, file_rows: FileRows | None = None
) -> tuple[NDArray[np.float64], bool]:
    """Convert a numeric (n, 3) array of any layout to a new C-contiguous float64 array.

    Block by block, so that each block is checked for finiteness while it is in cache: the
    input block when it is contiguous native floats (half the bytes of float32 data), else the
    float64 output block. Unaligned input (a binary body after a header of any length) is
    first copied into an aligned scratch block: numpy's unaligned casts are about twice as slow
    as a copy.

    One core moves only so many bytes per second through its caches (~30 GB/s here, and a
    float32 -> float64 widening reads 12 and writes 24 bytes per point), so with ``threads``
    >= 2 and at least :data:`PARALLEL_MIN_POINTS` rows per thread, helper threads take blocks
    too (numpy's copies and ``dot`` release the GIL). The blocks are handed out one at a time
    from a shared counter, not split up front: a helper that gets no core on a busy machine
    then simply converts fewer blocks (none at worst), and the caller never waits for more than
    the block a helper is converting. The result does not depend on ``threads``.

    Parameters
    ----------
    array : ndarray, shape (n, 3), any real or integer dtype, any strides and alignment
    threads : int
        Threads to use (the calling thread included).
    file_rows : FileRows, optional
        ``array`` is a view of a memory-mapped file lying there: blocks are read from the file
        instead of through the map.

    Returns
    -------
    points : ndarray, shape (n, 3), float64
    all_finite : bool
        True only when every coordinate is finite (False: check row by row).
    """
    out = np.empty(array.shape, dtype=np.float64)
    results = _share_blocks(
        len(array),
        threads,
        lambda block_numbers: _convert_blocks(array, out, block_numbers, file_rows),
        "from_array",
    )
    return out, all(results)


Shared = TypeVar("Shared")


def _share_blocks(
    n_rows: int, threads: int, work: Callable[[Iterator[int]], Shared], name: str
) -> list[Shared]:
    """Run ``work`` on the calling thread and on helper threads, all taking block numbers from
    one counter, with at least :data:`PARALLEL_MIN_POINTS` of the ``n_rows`` rows per thread;
    the results of every thread that ran (the caller's first).

    The blocks are handed out one at a time, not split up front: a helper that gets no core
    on a busy machine then simply takes fewer blocks (none at worst), and the caller never
    waits for more than the block a helper is working on. A helper that cannot be started
    (e.g. under an address-space limit) leaves its blocks to the others; an exception in a
    helper is raised in the caller.
    """
    n_threads = max(1, min(threads, n_rows // PARALLEL_MIN_POINTS))
    if n_threads == 1:
        return [work(itertools.count())]
    # itertools.count's next() is atomic (one C call under the GIL): each block goes to
    # exactly one thread.
    block_numbers = itertools.count()
    results: list[Shared] = []
    failures: list[BaseException] = []

    def run() -> None:
        try:
            results.append(work(block_numbers))
        except BaseException as exc:  # re-raised in the calling thread
            failures.append(exc)

    helpers: list[threading.Thread] = []
    for number in range(1, n_threads):
        helper = threading.Thread(target=run, name=f"{name}-{number}")
        try:
            helper.start()
        except RuntimeError:  # no thread to be had (e.g. an address-space limit)
            break  # the threads already running (at least the caller) take every block
        helpers.append(helper)
    run()
    for helper in helpers:
        helper.join()
    if failures:
        raise failures[0]
    return results


def _checked_coordinates(points: NDArray) -> NDArray:
    """``points`` as an array of shape (n, 3) with n > 0, else :class:`PointCloudError`."""
    array = np.asarray(points)
    if array.ndim != 2 or array.shape[1] != 3:
        raise PointCloudError(
            f"points must have shape (n, 3), got {array.shape}; give x, y, z per point"
        )
    _check_not_empty(int(array.shape[0]))
    return array


def _check_not_empty(n_source: int) -> None:
    if n_source == 0:
        raise PointCloudError("the point cloud is empty (0 points)")


def _as_float64(array: NDArray) -> NDArray[np.float64]:
    """``array`` as float64 (no copy when it is already), else :class:`PointCloudError`."""
    try:
        return array.astype(np.float64, copy=False)
    except (TypeError, ValueError) as exc:
        raise PointCloudError(f"coordinates are not numbers: {exc}") from exc


def _check_finite_count(n_finite: int, n_source: int, min_points: int) -> None:
    """Refuse a cloud with no finite point, or fewer than ``min_points``."""
    if n_finite == 0:
        raise PointCloudError(
            f"none of the {n_source} points has finite coordinates (all contain NaN or inf)"
        )
    if n_finite < min_points:
        raise PointCloudError(
            f"only {n_finite} finite points (of {n_source}); at least {min_points} are needed"
        )


def _checked_attributes(
    attributes: Mapping[str, NDArray] | None, n_source: int
) -> dict[str, NDArray]:
    """The per-point fields as arrays, each with one row per source row."""
    checked: dict[str, NDArray] = {}
    for name, values in (attributes or {}).items():
        values = np.asarray(values)
        if values.shape[:1] != (n_source,):
            raise PointCloudError(
                f"attribute {name!r} has {values.shape[0] if values.ndim else 0} rows, "
                f"expected {n_source} (one per point)"
            )
        checked[name] = values
    return checked


def _checked_sensor_origin(sensor_origin: NDArray | None) -> NDArray[np.float64] | None:
    """The sensor origin as a finite float64 (3,) array (None stays None)."""
    if sensor_origin is None:
        return None
    origin = np.asarray(sensor_origin, dtype=np.float64).reshape(3)
    if not np.isfinite(origin).all():
        raise PointCloudError(f"sensor origin {origin.tolist()} is not finite")
    return origin


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
    sensor_origin : ndarray, shape (3,), float64, or None
    """

    n_source: int
    n_points: int
    low: NDArray[np.float64]
    high: NDArray[np.float64]
    sensor_origin: NDArray[np.float64] | None = None

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
    sensor_origin : array_like, shape (3,), optional
    min_points : int
        Raise :class:`PointCloudError` when fewer finite points remain.
    threads : int, optional
        Threads that share the blocks (as for :meth:`PointCloud.from_array`); default
        :func:`conversion_threads`. The summary does not depend on it.
    file_rows : FileRows, optional
        Where ``points``, a view of a memory-mapped file, lies in that file (read with
        ``pread``, see :class:`FileRows`).

    Returns
    -------
    CloudSummary

    Raises
    ------
    PointCloudError
        Wrong shape, no finite points, fewer than ``min_points`` finite points, attributes
        with the wrong number of rows, a non-finite sensor origin.
    """
    array = _checked_coordinates(points)
    n_source = int(array.shape[0])
    if array.dtype.kind not in "iuf":
        array = _as_float64(array)
        file_rows = None
    parts = _share_blocks(
        n_source,
        conversion_threads() if threads is None else threads,
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
    for _, block in _blocks(array, block_numbers, file_rows, True, SUMMARY_BLOCK_POINTS):
        bounds.add(block)
    return bounds


class FiniteBounds:
    """Counts the finite rows of coordinate blocks and bounds them, one block at a time.

    What :func:`summarise_array` (and a reader that decodes in chunks) keeps of a cloud: a
    few kilobytes whatever its size. Each block's whole lines of :data:`SUMMARY_ROWS_PER_LINE`
    rows are reduced to a line of minima and one of maxima in the data's own type: numpy's
    min/max propagate NaN and reach inf, so the two lines also prove the block finite (their
    ``dot`` is finite; it may overflow, see :func:`_surely_finite`), without a pass of its
    own. A block with a non-finite value, and a block's last partial line, are checked row by
    row.
    """

    def __init__(self) -> None:
        self.n_finite = 0
        self.low = np.full(3, np.inf)  # of the rows checked row by row
        self.high = np.full(3, -np.inf)
        self.line_low: NDArray | None = None  # running extremes of whole lines, (rows * 3,)
        self.line_high: NDArray | None = None

    def add(self, block: NDArray) -> None:
        """Count and bound the finite rows of ``block``, shape (k, 3), any real or integer
        dtype, C-contiguous; the block may be overwritten afterwards."""
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
        """Add what ``other`` counted and bounded (another thread's blocks)."""
        self.n_finite += other.n_finite
        np.minimum(self.low, other.low, out=self.low)
        np.maximum(self.high, other.high, out=self.high)
        if other.line_low is not None and other.line_high is not None:
            self._add_lines(other.line_low, other.line_high)

    def bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(low, high)`` of every finite row added, each shape (3,) float64 (inf and -inf
        when there was none)."""
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
        """The :class:`CloudSummary` of a source of ``n_source`` rows whose blocks were all
        added, after the checks of :meth:`PointCloud.from_array` (same errors)."""
        _check_not_empty(n_source)
        _check_finite_count(self.n_finite, n_source, min_points)
        _checked_attributes(attributes, n_source)
        low, high = self.bounds()
        return CloudSummary(
            n_source, self.n_finite, low, high, _checked_sensor_origin(sensor_origin)
        )


class _BlockReader:
    """Reads rows of a file-backed (n, 3) view into an aligned buffer with ``os.preadv``."""

    def __init__(self, array: NDArray, file_rows: FileRows, block_points: int):
        self.file_rows = file_rows
        self.dtype = array.dtype
        self.strides = array.strides  # (row stride, column step) in the file
        row_stride, step = array.strides
        if row_stride <= 0 or step <= 0:
            raise ValueError("file rows must have positive strides")
        self.row_bytes = 2 * step + array.dtype.itemsize  # x .. end of z within a row
        # 8-byte aligned: any column offset keeps the dtype's alignment when the file's does
        self.buffer = np.empty(
            -(-(block_points * row_stride + self.row_bytes) // 8), dtype=np.uint64
        )

    def read(self, start: int, rows: int) -> NDArray:
        """Rows ``start .. start + rows`` as an (rows, 3) view of the buffer."""
        row_stride = self.strides[0]
        size = (rows - 1) * row_stride + self.row_bytes
        view = memoryview(self.buffer).cast("B")[:size]
        got = os.preadv(
            self.file_rows.file_descriptor, [view], self.file_rows.offset + start * row_stride
        )
        if got != size:
            raise PointCloudError(
                f"the file changed while it was read: {got} of {size} bytes at row {start}"
            )
        return np.ndarray((rows, 3), self.dtype, self.buffer, 0, self.strides)


def _blocks(
    array: NDArray,
    block_numbers: Iterator[int],
    file_rows: FileRows | None = None,
    contiguous: bool = False,
    block_points: int | None = None,
) -> Iterator[tuple[int, NDArray]]:
    """The blocks of ``array`` (shape (n, 3)) that ``block_numbers`` hands out, as ``(start,
    block)``, until it hands out one past the end.

    With ``file_rows`` each block's bytes are read from the file into a buffer first (see
    :class:`FileRows`). A block is aligned (unaligned rows are copied into a scratch block:
    numpy's unaligned casts are about twice as slow as a copy) and, with ``contiguous``,
    C-contiguous (padded records are copied too). A yielded block may be overwritten by the
    next one. Blocks have ``block_points`` rows (default :data:`CHECK_BLOCK_POINTS`), the last
    one maybe fewer.
    """
    size = CHECK_BLOCK_POINTS if block_points is None else block_points
    scratch = None  # allocated on first use: most files need none
    reader = None if file_rows is None else _BlockReader(array, file_rows, size)
    for number in block_numbers:
        start = number * size
        if start >= len(array):
            return
        block = array[start : start + size]
        if reader is not None:
            block = reader.read(start, len(block))
        if not block.flags.aligned or (contiguous and not block.flags.c_contiguous):
            if scratch is None:
                scratch = np.empty((size, 3), array.dtype.newbyteorder("="))
            np.copyto(scratch[: len(block)], block)
            block = scratch[: len(block)]
        yield start, block


def _convert_blocks(
    array: NDArray,
    out: NDArray[np.float64],
    block_numbers: Iterator[int],
    file_rows: FileRows | None = None,
) -> bool:
    """Widen the blocks of ``array`` (shape (n, 3)) that ``block_numbers`` hands out into
    ``out`` (shape (n, 3), float64), until it hands out one past the end; with ``file_rows``
    each block's bytes are read from the file into a buffer first (see :class:`FileRows`).

    Returns
    -------
    bool
        True only when every value converted here is finite (see :func:`_float64_checked`).
    """
    check_input = array.dtype.kind == "f"
    all_finite = True
    # Signalling NaNs raise the "invalid" flag when widened: they are NaN rows like any other;
    # dot() may overflow (see _surely_finite). One errstate for all blocks (it costs ~5 us).
    with np.errstate(invalid="ignore", over="ignore"):
        for start, block in _blocks(array, block_numbers, file_rows):
            target = out[start : start + len(block)]
            in_place = check_input and block.dtype.isnative and block.flags.c_contiguous
            if all_finite and in_place:
                flat = block.reshape(-1)
                all_finite = math.isfinite(np.dot(flat, flat))
            np.copyto(target, block, casting="unsafe")
            if all_finite and not in_place:
                flat = target.reshape(-1)
                all_finite = math.isfinite(np.dot(flat, flat))
    return all_finite


@dataclass(frozen=True, eq=False)
class PointCloud:
    """Finite 3D points plus optional per-point attributes.

    Attributes
    ----------
    points : ndarray, shape (n, 3), float64
        Finite coordinates, in the file's frame and units.
    source_index : ndarray, shape (n,), int64
        Row of each point in the source (file order); strictly increasing. ``None`` given to
        the constructor means no row was dropped: the ``arange`` is then built on first use.
    n_source : int
        Number of rows in the source, including dropped non-finite rows.
    attributes : mapping of str to ndarray, each shape (n, ...)
        Extra per-point fields kept from the file (intensity, rgb, normals, ...).
    sensor_origin : ndarray, shape (3,), float64, or None
        Where the sensor was when the scan was taken, in the same frame as ``points``, when
        known (a PCD ``VIEWPOINT``, a synthetic scene, or given by the caller).
    """

    points: NDArray[np.float64]
    source_index: NDArray[np.int64] = _SourceIndex()  # type: ignore[assignment]
    n_source: int
    attributes: Mapping[str, NDArray] = field(default_factory=dict)
    sensor_origin: NDArray[np.float64] | None = None

    @classmethod
    def from_array(
        cls,
        points: NDArray,
        attributes: Mapping[str, NDArray] | None = None,
        sensor_origin: NDArray | None = None,
        min_points: int = MIN_POINTS,
        threads: int | None = None,
        file_rows: FileRows | None = None,
    ) -> PointCloud:
        """Validate raw coordinates, drop non-finite rows and build a cloud.

        Parameters
        ----------
        points : array_like, shape (n, 3)
            Coordinates in file order; converted to float64.
        attributes : mapping of str to array_like, each shape (n, ...), optional
            Per-point fields in the same order; rows are dropped together with the points.
        sensor_origin : array_like, shape (3,), optional
            Sensor position in the same frame.
        min_points : int
            Raise :class:`PointCloudError` when fewer finite points remain.
        threads : int, optional
            Threads that convert a large non-float64 ``points`` (e.g. a float32 view of a
            file) to float64; default :func:`conversion_threads`. The cloud does not depend
            on it.
        file_rows : FileRows, optional
            Where ``points``, a view of a memory-mapped file, lies in that file: it is then
            read block by block from the file (faster than through the map; same cloud).

        Raises
        ------
        PointCloudError
            Wrong shape, no finite points, or fewer than ``min_points`` finite points.
        """
        array = _checked_coordinates(points)
        n_source = int(array.shape[0])
        if array.dtype.kind in "iuf" and not _is_owned_float64(array):
            # Readers hand over (n, 3) views of the file (float32, big endian, padded records):
            # one pass converts them to an owned float64 array and checks finiteness on the way.
            if threads is None:
                threads = conversion_threads()
            array, all_finite = _float64_checked(array, threads, file_rows)
        else:
            array = _as_float64(array)
            all_finite = _surely_finite(array)
        if all_finite:
            finite = None
            n_finite = n_source
        else:
            finite = np.isfinite(array).all(axis=1)
            n_finite = int(finite.sum())
        _check_finite_count(n_finite, n_source, min_points)
        kept_attributes = {
            name: values if finite is None else values[finite]
            for name, values in _checked_attributes(attributes, n_source).items()
        }
        origin = _checked_sensor_origin(sensor_origin)
        source_index: NDArray[np.int64] | None
        if n_finite == n_source:
            kept_points = np.ascontiguousarray(array)
            source_index = None  # every row kept: the arange is built on first use
        else:
            kept_points = np.ascontiguousarray(array[finite])
            source_index = np.flatnonzero(finite).astype(np.int64)
        return cls(kept_points, source_index, n_source, kept_attributes, origin)  # type: ignore[arg-type]

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def n_dropped(self) -> int:
        """Number of source rows dropped because a coordinate was NaN or inf."""
        return self.n_source - len(self)

    def to_source_order(self, values: NDArray, fill: object) -> NDArray:
        """Scatter per-point ``values`` (shape (n, ...)) back to file order, ``fill`` elsewhere.

        Returns
        -------
        ndarray, shape (n_source, ...)
        """
        values = np.asarray(values)
        if values.shape[:1] != (len(self),):
            raise ValueError(f"expected {len(self)} values, got {values.shape[0]}")
        out = np.full((self.n_source, *values.shape[1:]), fill, dtype=values.dtype)
        if self._all_rows_kept:
            out[...] = values
        else:
            out[self.source_index] = values
        return out

    def from_source_order(self, values: NDArray) -> NDArray:
        """The entries of per-row ``values`` (file order) that belong to this cloud's points.

        The inverse of :meth:`to_source_order`: labels saved per file row (dropped rows
        included) come back aligned with ``points``.

        Parameters
        ----------
        values : ndarray, shape (n_source, ...)

        Returns
        -------
        ndarray, shape (n, ...)

        Raises
        ------
        ValueError
            ``values`` has not one row per source row (it belongs to another file).
        """
        values = np.asarray(values)
        if values.shape[:1] != (self.n_source,):
            raise ValueError(
                f"{values.shape[0] if values.ndim else 0} values for a file of {self.n_source} "
                "rows: they belong to another file"
            )
        if self._all_rows_kept:
            return values.copy()
        return values[self.source_index]

    @property
    def _all_rows_kept(self) -> bool:
        """No row was dropped (``source_index`` is then ``arange(n_source)``, maybe not built)."""
        return self.__dict__.get("_source_index", ()) is None or self.n_source == len(self)

    def bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Axis-aligned bounding box ``(min, max)``, each shape (3,)."""
        return column_extreme(self.points, np.minimum), column_extreme(self.points, np.maximum)


EXTREME_ROWS_PER_LINE = 256
"""Rows folded into one line by :func:`column_extreme`."""


def column_extreme(points: NDArray, ufunc: np.ufunc) -> NDArray:
    """``ufunc.reduce(points, axis=0)`` (``np.minimum`` or ``np.maximum``), 10-15x faster.

    numpy reduces a C-contiguous (n, 3) array along axis 0 with a 3-element inner loop (44 ms
    for 1M points); folding :data:`EXTREME_ROWS_PER_LINE` rows into each line gives it a long,
    vectorised inner loop (3 ms). Same values, NaN propagation and errors as the plain reduce.

    Parameters
    ----------
    points : ndarray, shape (n, d)
    ufunc : numpy.minimum or numpy.maximum

    Returns
    -------
    ndarray, shape (d,)
    """
    points = np.asarray(points)
    rows = EXTREME_ROWS_PER_LINE
    n_folded = len(points) - len(points) % rows if points.ndim == 2 else 0
    if n_folded == 0 or not points.flags.c_contiguous:
        return ufunc.reduce(points, axis=0)
    width = points.shape[1]
    folded = ufunc.reduce(points[:n_folded].reshape(-1, rows * width), axis=0)
    extreme = ufunc.reduce(folded.reshape(rows, width), axis=0)
    if n_folded < len(points):
        extreme = ufunc(extreme, ufunc.reduce(points[n_folded:], axis=0))
    return extreme


def choose_local_origin(points: NDArray[np.float64], quantum: float = 1.0) -> NDArray[np.float64]:
    """A rounded point near the centre of ``points`` to subtract before numeric work.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    quantum : float
        The origin is a multiple of this (metres), so reported coordinates stay readable.

    Returns
    -------
    ndarray, shape (3,)
        Zero when the data is already near the origin (|centre| < 1 km), so local and file
        coordinates coincide for ordinary sensor-frame scans.
    """
    low = column_extreme(points, np.minimum)
    high = column_extreme(points, np.maximum)
    centre = (low + high) / 2.0
    if np.all(np.abs(centre) < 1000.0):
        return np.zeros(3)
    return np.round(centre / quantum) * quantum


def voxel_downsample_indices(points: NDArray[np.float64], voxel_size: float) -> NDArray[np.int64]:
    """Indices of one point per occupied voxel (the first in input order).

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    voxel_size : float
        Edge length of the cubic voxels, > 0.

    Returns
    -------
    ndarray, shape (k,), int64
        Sorted indices into ``points``; k <= n.
    """
    if voxel_size <= 0:
        raise ValueError("voxel_size must be positive")
    keys = np.floor((points - column_extreme(points, np.minimum)) / voxel_size).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return np.sort(first).astype(np.int64)
