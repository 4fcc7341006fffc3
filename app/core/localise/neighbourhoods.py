"""Every point's k nearest neighbours in its own cloud, found in line or on a thread of their own.

The k-NN query is the localiser's largest single cost, so a caller may start it ahead of time,
e.g. for the reference while the scan is still being aligned (:func:`start_neighbourhood_search`).
"""

from __future__ import annotations

import importlib
import itertools
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree
from threadpoolctl import threadpool_limits

from app.core.cloud import as_points
from app.core.errors import InputError, PointCloudError
from app.core.localise.settings import QUERY_CHUNK, resolve_parameters
from app.core.spatial_order import ordered_chunks, spatial_order
from app.core.threads import concurrently, for_each_chunk


def _compiled_kernel() -> Any:
    """The compiled k-NN (``_knn_kernel.c``), or None when setup.py found no C compiler.

    Imported by name, as ``surface.py`` imports its plane kernel (a leaf module)."""
    try:
        return importlib.import_module("app.core.localise._knn_kernel")
    except ImportError:  # pragma: no cover - depends on the install
        return None


KNN_KERNEL: Any = _compiled_kernel()
"""The compiled k-NN of :func:`nearest_neighbourhoods`, or None when it was not built: then
pykdtree's queries run a chunk at a time, to the same neighbours."""
KERNEL_MAX_NEIGHBOURS = 256
"""The kernel's limit on k + 1 (``MAX_NEIGHBOURS`` in ``_knn_kernel.c``)."""
LEAF_BLOCKS = 32
"""Blocks of the kernel tree's leaves that two threads share (~1k leaves, ~30k points each
at 1M points): a thread finishes at most one block after the other."""

__all__ = [
    "KNN_KERNEL",
    "NeighbourhoodSearch",
    "Neighbourhoods",
    "Surfaces",
    "kernel_nearest",
    "kernel_self_neighbours",
    "nearest_neighbourhoods",
    "neighbourhood_size",
    "start_neighbourhood_search",
]


@dataclass(frozen=True)
class Surfaces:
    """The local surfaces fitted to a cloud's neighbourhoods
    (:func:`~app.core.localise.surface.fit_surfaces`; fields as in
    :class:`~app.core.localise.surface.LocalGeometry`).

    Attributes
    ----------
    normal : ndarray, shape (n, 3), float32
    plane_constant : ndarray, shape (n,), float64
    spacing : ndarray, shape (n,), float64
    noise : float
    linear : ndarray, shape (n,), bool
    variation : ndarray, shape (n,), float64
    """

    normal: NDArray[np.float32]
    plane_constant: NDArray[np.float64]
    spacing: NDArray[np.float64]
    noise: float
    linear: NDArray[np.bool_]
    variation: NDArray[np.float64]


@dataclass(frozen=True)
class Neighbourhoods:
    """A cloud's KD-tree and every point's nearest neighbours (:func:`nearest_neighbourhoods`).

    Attributes
    ----------
    tree : pykdtree.kdtree.KDTree
        Over the cloud's points.
    neighbor_index : ndarray, shape (n, k + 1), uint32
        Column 0 is the point itself.
    kth_distance : ndarray, shape (n,), float64
        Distance to the k-th neighbour.
    order : ndarray, shape (n,), intp, or None
        A spatial order of the cloud (the compiled kernel's tree order, or
        :func:`~app.core.spatial_order.spatial_order`), with which later passes over the cloud
        visit it chunk by chunk of nearby points (None: file order).
    surfaces : Surfaces or None
        Fitted already (e.g. read from a reference's geometry cache), or None.
    kernel_tree : object or None
        The compiled kernel's k-d tree of the cloud (:func:`nearest_neighbourhoods` found the
        neighbours with it), kept for :func:`kernel_nearest`; None without it.
    """

    tree: KDTree
    neighbor_index: NDArray[np.uint32]
    kth_distance: NDArray[np.float64]
    order: NDArray[np.intp] | None = None
    surfaces: Surfaces | None = None
    kernel_tree: Any = None


def neighbourhood_size(n_points: int, **params: Any) -> int:
    """The k that ``localise_changes`` uses for a cloud of ``n_points`` with ``params``.

    Raises
    ------
    InputError
        An unknown or invalid parameter (the message ``localise_changes`` would give).
    """
    return min(resolve_parameters(params)["n_neighbors"], n_points - 1)


def nearest_neighbourhoods(
    points: NDArray[np.float64],
    n_neighbors: int,
    _cancelled: CancelEvent | None = None,
    *,
    threads: int = 1,
) -> Neighbourhoods | None:
    """Build the KD-tree of ``points`` and find each point's ``n_neighbors`` nearest neighbours.

    By the compiled kernel when it was built (:data:`KNN_KERNEL`, ~20 % less CPU at 1M points,
    without the GIL throughout; the same neighbours, see :func:`_compiled_neighbours`), else by
    the tree's queries in chunks, so only the k-th distance is kept (never an (n, k + 1) float
    array).  The chunks follow a spatial order of the cloud (:func:`_spatial_order`: the
    kernel tree's, else :func:`~app.core.spatial_order.spatial_order`; nearby points together:
    the tree walks stay in cache, about 4x faster on a shuffled 1M-point cloud; each point's
    answer is the same in any order).  The query releases the GIL:
    :class:`NeighbourhoodSearch` runs this on its own thread.

    Parameters
    ----------
    points : ndarray, shape (n, 3), float64
        Finite coordinates, n >= 2 (the cloud ``localise_changes`` will be given: the same
        array, not a copy in another frame).
    n_neighbors : int
        k, in 1..n - 1 (see :func:`neighbourhood_size`).
    threads : int
        Threads of the compiled kernel (the tree's queries follow OpenMP's setting).

    Returns
    -------
    Neighbourhoods
        (None only when ``_cancelled``, :class:`NeighbourhoodSearch`'s event, was set.)
    """
    n = points.shape[0]
    k = int(n_neighbors)
    if not 1 <= k <= n - 1:
        raise ValueError(f"n_neighbors must be in 1..{n - 1}, got {n_neighbors}")
    tree = KDTree(points)
    own_tree = _kernel_tree(points, k)
    order = _spatial_order(points, own_tree)
    neighbor_index = np.empty((n, k + 1), dtype=np.uint32)
    kth_distance = np.empty(n)
    found = own_tree is not None and _compiled_neighbours(
        own_tree, points, k, neighbor_index, kth_distance, tree, _cancelled, threads
    )
    if found is None:
        return None
    if not found:
        for rows in ordered_chunks(order, n, QUERY_CHUNK):
            if _cancelled is not None and _cancelled.is_set():
                return None
            squared, neighbor_index[rows] = tree.query(points[rows], k=k + 1, sqr_dists=True)
            kth_distance[rows] = np.sqrt(squared[:, k])
    return Neighbourhoods(
        tree, neighbor_index, kth_distance, order, kernel_tree=own_tree if found else None
    )


def _by_leaf_blocks(search: Callable[[int, int], int], own_tree: Any, threads: int) -> list[int]:
    """``search(first, last)`` over the leaves of the kernel's tree ``own_tree``: one call
    (leaves 0 .. -1: all) below 2 ``threads``, else :data:`LEAF_BLOCKS` blocks of leaves that
    the threads take in turn (each block writes its own points' rows: the same arrays); the
    calls' results."""
    if threads < 2:
        return [search(0, -1)]
    n_leaves = KNN_KERNEL.leaf_count(own_tree)
    bounds = [n_leaves * block // LEAF_BLOCKS for block in range(LEAF_BLOCKS + 1)]
    found: list[int] = []

    def block(number: int) -> None:
        found.append(search(bounds[number], bounds[number + 1]))

    for_each_chunk(block, range(LEAF_BLOCKS), threads)
    return found


def kernel_nearest(
    points: NDArray[np.float64], own_tree: Any, other_tree: Any, other: KDTree, threads: int = 1
) -> tuple[NDArray[np.float64], NDArray[np.uint32]] | None:
    """Each point's nearest point in another cloud by the compiled kernel: the same numbers
    as ``other.query(points, k=1)``, to the bit, or None when the kernel cannot search them.

    The kernel walks ``other_tree`` once per leaf of ``own_tree`` (both its trees, from
    :func:`nearest_neighbourhoods`), without the GIL; each squared distance is computed as
    pykdtree computes it.  A point with two nearest points equally far (which one pykdtree
    gives is its walk's) is asked of ``other``.

    Parameters
    ----------
    points : ndarray, shape (p, 3), float64
        The points ``own_tree`` was built over.
    own_tree, other_tree : object
        The kernel's trees of ``points`` and of the other cloud
        (:attr:`Neighbourhoods.kernel_tree`).
    other : pykdtree.kdtree.KDTree
        Over the other cloud's points.
    threads : int
        From 2, blocks of ``own_tree``'s leaves on that many threads (:func:`_by_leaf_blocks`:
        the other direction, on a thread of its own, may finish first).

    Returns
    -------
    distance : ndarray, shape (p,), float64
    index : ndarray, shape (p,), uint32
    """
    count = points.shape[0]
    index = np.empty(count, dtype=np.uint32)
    distance = np.empty(count)
    tie = np.empty(count, dtype=np.uint8)

    def search(first: int, last: int) -> int:
        return KNN_KERNEL.nearest_other(own_tree, other_tree, index, distance, tie, first, last)

    try:
        ties = sum(_by_leaf_blocks(search, own_tree, threads))
    except (ValueError, BufferError):  # e.g. thousands of equal points: left to the tree
        return None
    np.sqrt(distance, out=distance)
    if ties:
        rows = np.flatnonzero(tie)
        for first in range(0, rows.size, QUERY_CHUNK):
            chunk = rows[first : first + QUERY_CHUNK]
            distance[chunk], index[chunk] = other.query(points[chunk], k=1)
    return distance, index


def kernel_self_neighbours(
    points: NDArray[np.float64], n_neighbors: int, threads: int = 1
) -> tuple[NDArray[np.uint32], NDArray[np.bool_]] | None:
    """Each point's ``n_neighbors`` nearest points in its own cloud by the compiled kernel,
    on ``threads`` threads (:func:`_by_leaf_blocks`), with the points whose answer is not
    unique flagged, not resolved.

    The same neighbours as pykdtree's query with ``k = n_neighbors + 1``, to the bit, wherever
    ``tie`` is False (see :func:`_compiled_neighbours`); where it is True (two of the
    ``n_neighbors + 1`` nearest equally far) the caller asks its own query.

    Parameters
    ----------
    points : ndarray, shape (c, 3), float64
        C-contiguous.
    n_neighbors : int
        k, in 1..c - 1.
    threads : int

    Returns
    -------
    index : ndarray, shape (c, k + 1), uint32
        Column 0 is the point itself where ``tie`` is False.
    tie : ndarray, shape (c,), bool
    None
        The kernel was not built or cannot search these points.
    """
    k = int(n_neighbors)
    own_tree = _kernel_tree(points, k)
    if own_tree is None:
        return None
    count = points.shape[0]
    index = np.empty((count, k + 1), dtype=np.uint32)
    tie = np.empty(count, dtype=np.uint8)
    kth_squared = np.empty(count)
    never = np.zeros(1, dtype=np.uint8)

    def search(first: int, last: int) -> int:
        kernel = KNN_KERNEL
        return kernel.self_neighbours(own_tree, k + 1, index, kth_squared, tie, never, first, last)

    try:
        _by_leaf_blocks(search, own_tree, threads)
    except (ValueError, BufferError):  # e.g. thousands of equal points
        return None
    return index, tie.view(np.bool_)


def _kernel_tree(points: NDArray[np.float64], k: int) -> Any:
    """The compiled kernel's k-d tree of ``points`` (n, 3), or None when the kernel cannot
    search it for ``k`` neighbours (not built, points it refuses)."""
    kernel = KNN_KERNEL
    if kernel is None or not points.flags.c_contiguous or k + 1 >= KERNEL_MAX_NEIGHBOURS:
        return None
    try:
        return kernel.build_tree(points)
    except (ValueError, BufferError):
        return None


def _spatial_order(points: NDArray[np.float64], own_tree: Any) -> NDArray[np.intp]:
    """A spatial order of ``points`` (n, 3), shape (n,): the rows of the kernel tree's points
    (``own_tree``, None: none), leaf after leaf (each leaf's up to 32 points together,
    neighbouring leaves mostly next to each other), which costs a copy, else
    :func:`~app.core.spatial_order.spatial_order`, which sorts Morton codes (~0.08 CPU s a 1M
    cloud).  Every pass that follows an order gives each point the same answer in any order."""
    if own_tree is not None and np.dtype(np.intp).itemsize == 8:
        order = np.empty(points.shape[0], dtype=np.intp)
        KNN_KERNEL.tree_order(own_tree, order)
        return order
    return spatial_order(points)


def _compiled_neighbours(
    own_tree: Any,
    points: NDArray[np.float64],
    k: int,
    neighbor_index: NDArray[np.uint32],
    kth_distance: NDArray[np.float64],
    tree: KDTree,
    cancelled: CancelEvent | None,
    threads: int = 1,
) -> bool | None:
    """:func:`nearest_neighbourhoods`' neighbours by the compiled kernel (``_knn_kernel.c``)
    from its tree of ``points`` (:func:`_kernel_tree`): ``neighbor_index`` (n, k + 1) and
    ``kth_distance`` (n,) filled in; False when it cannot (points it refuses: then nothing is
    written), None when ``cancelled``.

    The same numbers as pykdtree's queries, to the bit: the kernel computes each squared
    distance as pykdtree does, and the points whose k + 1 nearest are not all at different
    distances (their order among equals is the KD-tree walk's) are queried with ``tree``.  The
    k-th distance is the root of the squared one, as pykdtree takes it (IEEE square roots are
    exact to the last bit).  One call without the GIL (a search running beside the alignment
    waits for no GIL hand-over), or blocks of leaves shared by two on ``threads`` >= 2
    (:data:`LEAF_BLOCKS`); ``cancelled`` stops it at its next
    leaf of ~16 points.
    """
    kernel = KNN_KERNEL
    tie = np.empty(points.shape[0], dtype=np.uint8)
    flag = getattr(cancelled, "flag", None)
    flag = np.zeros(1, dtype=np.uint8) if flag is None else flag
    try:
        # the leaves in blocks that ``threads`` threads take one at a time from one counter
        # (each writes its own points' rows): a thread whose blocks were slower, or which got
        # less of a core, leaves the rest to the other instead of finishing alone
        n_leaves = kernel.leaf_count(own_tree)
        n_blocks = LEAF_BLOCKS if threads >= 2 else 1
        bounds = [n_leaves * block // n_blocks for block in range(n_blocks + 1)]
        block_numbers = itertools.count()  # next() is one C call under the GIL: atomic

        def leaves() -> int:
            ties = 0
            for block in block_numbers:
                if block >= n_blocks:
                    return ties
                found = kernel.self_neighbours(
                    own_tree,
                    k + 1,
                    neighbor_index,
                    kth_distance,
                    tie,
                    flag,
                    bounds[block],
                    bounds[block + 1],
                )
                if found < 0:  # cancelled
                    return found
                ties += found
            return ties

        counts = concurrently(threads, leaves, leaves)
    except (ValueError, BufferError):  # e.g. thousands of equal points: left to the tree
        return False
    if min(counts) < 0:
        return None
    ties = sum(counts)
    np.sqrt(kth_distance, out=kth_distance)
    if ties:
        rows = np.flatnonzero(tie)
        for first in range(0, rows.size, QUERY_CHUNK):
            chunk = rows[first : first + QUERY_CHUNK]
            squared, neighbor_index[chunk] = tree.query(points[chunk], k=k + 1, sqr_dists=True)
            kth_distance[chunk] = np.sqrt(squared[:, k])
    return True


class CancelEvent(threading.Event):
    """A :class:`threading.Event` that the compiled kernel sees too: :attr:`flag` holds 1 once
    it is set (the kernel's loop reads it without the GIL)."""

    def __init__(self) -> None:
        super().__init__()
        self.flag = np.zeros(1, dtype=np.uint8)

    def set(self) -> None:
        """Set the event and the flag."""
        self.flag[0] = 1
        super().set()


class NeighbourhoodSearch:
    """:func:`nearest_neighbourhoods` of a cloud, running on its own thread from creation.

    :meth:`take` waits for it and hands the result over: the search keeps no reference, so the
    memory goes as soon as the caller lets go of it (the localiser releases the neighbour index
    half-way).  :meth:`cancel` stops it at its next chunk (~65k points) and waits.

    Parameters
    ----------
    points : ndarray, shape (n, 3), float64
        Finite coordinates; the array ``localise_changes`` will be given.
    n_neighbors : int
        k (:func:`neighbourhood_size`).
    openmp_threads : int
        OpenMP threads of the search's own KD-tree queries (1 when it shares the machine with
        other work).
    on_found : callable, optional
        Called with the result on the search's thread before :meth:`take` can return it
        (e.g. to write it to a :class:`~app.core.cache.geometry.GeometryCache`).
    stored : callable, optional
        Tried first on the search's thread: its neighbourhoods, if not None, are the result
        (e.g. a :class:`~app.core.cache.geometry.GeometryCache`'s load); ``on_found`` is not
        called for them.
    finish : callable, optional
        Applied on the search's thread to the neighbourhoods found (before ``on_found``): what
        it returns is the result (e.g. with their surfaces fitted, to be cached with them).
    """

    def __init__(
        self,
        points: NDArray[np.float64],
        n_neighbors: int,
        openmp_threads: int = 1,
        on_found: Callable[[Neighbourhoods], object] | None = None,
        stored: Callable[[], Neighbourhoods | None] | None = None,
        finish: Callable[[Neighbourhoods], Neighbourhoods] | None = None,
    ):
        self._on_found = on_found
        self._stored = stored
        self._finish = finish
        self._cancelled = CancelEvent()
        self._result: Neighbourhoods | None = None
        self._error: BaseException | None = None
        self._thread = threading.Thread(
            target=self._run,
            args=(points, int(n_neighbors), openmp_threads),
            name="neighbourhood-search",
            daemon=True,
        )
        self._thread.start()

    def _run(self, points: NDArray[np.float64], n_neighbors: int, openmp_threads: int) -> None:
        try:
            found = None if self._stored is None else self._stored()
            if found is not None:
                self._result = found
                return
            # the limit applies to this thread's own OpenMP calls only
            with threadpool_limits(limits=openmp_threads, user_api="openmp"):
                result = nearest_neighbourhoods(
                    points, n_neighbors, self._cancelled, threads=openmp_threads
                )
                if result is not None and self._finish is not None:
                    result = self._finish(result)
            if result is not None and self._on_found is not None:
                self._on_found(result)
            self._result = result
        except BaseException as error:  # handed to take()'s caller
            self._error = error

    def take(self) -> Neighbourhoods:
        """Wait for the search and return its result (once; it keeps no reference)."""
        self._thread.join()
        if self._error is not None:
            raise self._error
        result, self._result = self._result, None
        if result is None:
            raise RuntimeError("the neighbourhood search was cancelled or already taken")
        return result

    def cancel(self) -> None:
        """Stop the search at its next chunk, wait for the thread and drop any result."""
        self._cancelled.set()
        self._thread.join()
        self._result = None


def start_neighbourhood_search(
    reference: NDArray,
    *,
    on_found: Callable[[Neighbourhoods], object] | None = None,
    stored: Callable[[], Neighbourhoods | None] | None = None,
    finish: Callable[[Neighbourhoods], Neighbourhoods] | None = None,
    openmp_threads: int = 1,
    **params: Any,
) -> NeighbourhoodSearch | None:
    """The :class:`NeighbourhoodSearch` that ``localise_changes(reference, ..., **params)`` can
    take as ``reference_neighbourhoods`` (or, for its scan, ``scan_neighbourhoods``), already
    running on ``openmp_threads`` OpenMP threads.

    Parameters
    ----------
    reference : array_like, shape (n, 3)
        The cloud, as ``localise_changes`` will be given it.
    on_found, stored, finish : callable, optional
        See :class:`NeighbourhoodSearch`.
    openmp_threads : int
        Threads of the search's KD-tree queries (1: it shares the machine with other work).
    **params
        Localisation keyword parameters (only ``n_neighbors`` matters here).

    Returns
    -------
    NeighbourhoodSearch or None
        None when ``localise_changes`` will reject ``reference`` or ``params`` (it then
        reports them itself) or when no thread can be started (e.g. under an address-space
        cap).
    """
    try:
        points = as_points(reference, "reference")
        n_neighbors = neighbourhood_size(len(points), **params)
        return NeighbourhoodSearch(
            points,
            n_neighbors,
            openmp_threads=max(1, int(openmp_threads)),
            on_found=on_found,
            stored=stored,
            finish=finish,
        )
    except (InputError, PointCloudError, RuntimeError):
        return None
