"""Reading an (n, 3) coordinate array a block at a time, on one thread or several.

A reader hands over a view of its file (float32, big endian, padded records, maybe memory
mapped); :func:`float64_checked` widens it to float64 and :func:`coordinate_blocks` yields it
in cache-sized blocks for summaries. With :class:`FileRows` the blocks are read from the file
with ``os.preadv`` instead of through the map, and :func:`share_blocks` lets helper threads
take blocks from one counter.
"""

from __future__ import annotations

import itertools
import math
import os
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from app.core.errors import PointCloudError
from app.core.threads import available_threads, configured_threads, usable_cpus

CHECK_BLOCK_POINTS = 1 << 15
"""Points converted per block in :meth:`PointCloud.from_array`: a block's input and float64
output (1.2 MB for float32 x, y, z) stay in the L2 cache while its finiteness is checked."""

PARALLEL_MIN_POINTS = 1 << 18
"""Fewest rows per thread when blocks are shared by several threads: fewer rows would not
repay starting a thread (figures in docs/performance.md)."""

MAX_CONVERSION_THREADS = 2
"""Most threads :func:`conversion_threads` suggests."""


@dataclass(frozen=True)
class FileRows:
    """Where a memory-mapped (n, 3) coordinate view lies in its file, to read it with ``pread``.

    Converting straight from a file's memory map pays a page-table walk and a first-touch
    fault on every page; reading each block with ``os.preadv`` into a cache-sized buffer and
    widening it there is faster (figures in docs/performance.md).

    Attributes
    ----------
    file_descriptor : int
        An open descriptor of the file (positional reads: threads may share it).
    offset : int
        Byte offset of the first row's first coordinate.
    """

    file_descriptor: int
    offset: int


def conversion_threads() -> int:
    """Threads :meth:`PointCloud.from_array` widens large inputs with by default.

    ``OMP_NUM_THREADS`` when set (the thread budget the service and the benchmarks give a
    process), at most :data:`MAX_CONVERSION_THREADS`. Otherwise the caller's thread plus one
    per CPU (of those this process may run on) that the machine's 1-minute load average
    leaves idle, like ``make -l``: a helper only pays when it gets a core of its own. On an
    oversubscribed machine a helper preempted while it holds the GIL stalls the caller for a
    whole time slice, so the rule errs towards one thread: the loss when oversubscribed is
    larger than the gain when not (figures in docs/performance.md).

    Returns
    -------
    int
        Between 1 and :data:`MAX_CONVERSION_THREADS`.
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


def float64_checked(
    array: NDArray, threads: int | None = None, file_rows: FileRows | None = None
) -> tuple[NDArray[np.float64], bool]:
    """Convert a numeric (n, 3) array of any layout to a new C-contiguous float64 array.

    Block by block, so that each block is checked for finiteness while it is in cache: the
    input block when it is contiguous native floats (half the bytes of float32 data), else the
    float64 output block. Unaligned input (a binary body after a header of any length) is
    first copied into an aligned scratch block: numpy's unaligned casts are about twice as slow
    as a copy.

    One core moves only so many bytes per second through its caches (a float32 -> float64
    widening reads 12 and writes 24 bytes per point), so with ``threads`` >= 2 and at least
    :data:`PARALLEL_MIN_POINTS` rows per thread, helper threads take blocks too (numpy's
    copies and ``dot`` release the GIL; see :func:`share_blocks`). The result does not depend
    on ``threads``.

    Parameters
    ----------
    array : ndarray, shape (n, 3), any real or integer dtype, any strides and alignment
    threads : int, optional
        Threads to use (the calling thread included); default :func:`conversion_threads`.
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
    results = share_blocks(
        len(array),
        threads,
        lambda block_numbers: _convert_blocks(array, out, block_numbers, file_rows),
        "from_array",
    )
    return out, all(results)


Shared = TypeVar("Shared")


def share_blocks(
    n_rows: int, threads: int | None, work: Callable[[Iterator[int]], Shared], name: str
) -> list[Shared]:
    """Run ``work`` on the calling thread and on helper threads, all taking block numbers from
    one counter, with at least :data:`PARALLEL_MIN_POINTS` of the ``n_rows`` rows per thread.

    The blocks are handed out one at a time, not split up front: a helper that gets no core
    on a busy machine then simply takes fewer blocks (none at worst), and the caller never
    waits for more than the block a helper is working on. A helper that cannot be started
    (e.g. under an address-space limit) leaves its blocks to the others; an exception in a
    helper is raised in the caller.

    Parameters
    ----------
    n_rows : int
        Rows of the array the blocks divide.
    threads : int or None
        Threads to use (the calling thread included); None: :func:`conversion_threads`.
    work : callable
        Takes the shared iterator of block numbers, works through the blocks it hands out
        (until one past the end) and returns its part of the result.
    name : str
        Prefix of the helper threads' names.

    Returns
    -------
    list
        What ``work`` returned on every thread that ran, the calling thread's first.
    """
    if threads is None:
        threads = conversion_threads()
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


def coordinate_blocks(
    array: NDArray,
    block_numbers: Iterator[int],
    file_rows: FileRows | None = None,
    contiguous: bool = False,
    block_points: int | None = None,
) -> Iterator[tuple[int, NDArray]]:
    """The blocks of ``array`` that ``block_numbers`` hands out, until it hands out one past
    the end.

    With ``file_rows`` each block's bytes are read from the file into a buffer first (see
    :class:`FileRows`). A block is aligned (unaligned rows are copied into a scratch block:
    numpy's unaligned casts are about twice as slow as a copy) and, with ``contiguous``,
    C-contiguous (padded records are copied too). A yielded block may be overwritten by the
    next one.

    Parameters
    ----------
    array : ndarray, shape (n, 3), any real or integer dtype, any strides and alignment
    block_numbers : iterator of int
        Hands out the numbers of the blocks to yield (maybe shared with other threads).
    file_rows : FileRows, optional
        Where ``array``, a view of a memory-mapped file, lies in that file.
    contiguous : bool
        Yield C-contiguous blocks.
    block_points : int, optional
        Rows per block, the last one maybe fewer; default :data:`CHECK_BLOCK_POINTS`.

    Yields
    ------
    start : int
        Row of ``array`` where the block starts.
    block : ndarray, shape (k, 3), the dtype of ``array`` in native byte order
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
        True only when every value converted here is finite (see :func:`float64_checked`).
    """
    check_input = array.dtype.kind == "f"
    all_finite = True
    # Signalling NaNs raise the "invalid" flag when widened: they are NaN rows like any other;
    # dot() may overflow (see cloud._surely_finite). One errstate for all blocks (~5 us each).
    with np.errstate(invalid="ignore", over="ignore"):
        for start, block in coordinate_blocks(array, block_numbers, file_rows):
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
