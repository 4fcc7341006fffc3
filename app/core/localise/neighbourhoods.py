"""Every point's k nearest neighbours in its own cloud, found in line or on a thread of their own.

The k-NN query is the localiser's largest single cost, so a caller may start it ahead of time,
e.g. for the reference while the scan is still being aligned (:func:`start_neighbourhood_search`).
"""

from __future__ import annotations

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

__all__ = [
    "NeighbourhoodSearch",
    "Neighbourhoods",
    "Surfaces",
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
        The cloud's :func:`~app.core.spatial_order.spatial_order`, with which later passes
        over the cloud visit it chunk by chunk of nearby points (None: file order).
    surfaces : Surfaces or None
        Fitted already (e.g. read from a reference's geometry cache), or None.
    """

    tree: KDTree
    neighbor_index: NDArray[np.uint32]
    kth_distance: NDArray[np.float64]
    order: NDArray[np.intp] | None = None
    surfaces: Surfaces | None = None


def neighbourhood_size(n_points: int, **params: Any) -> int:
    """The k that ``localise_changes`` uses for a cloud of ``n_points`` with ``params``.

    Raises
    ------
    InputError
        An unknown or invalid parameter (the message ``localise_changes`` would give).
    """
    return min(resolve_parameters(params)["n_neighbors"], n_points - 1)


def nearest_neighbourhoods(
    points: NDArray[np.float64], n_neighbors: int, _cancelled: threading.Event | None = None
) -> Neighbourhoods | None:
    """Build the KD-tree of ``points`` and find each point's ``n_neighbors`` nearest neighbours.

    Queried in chunks, so only the k-th distance is kept (never an (n, k + 1) float array).
    The chunks follow the cloud's :func:`~app.core.spatial_order.spatial_order` (nearby points
    together: the tree walks stay in cache, about 4x faster on a shuffled 1M-point cloud; each
    point's answer is the same in any order).  The query releases the GIL:
    :class:`NeighbourhoodSearch` runs this on its own thread.

    Parameters
    ----------
    points : ndarray, shape (n, 3), float64
        Finite coordinates, n >= 2 (the cloud ``localise_changes`` will be given: the same
        array, not a copy in another frame).
    n_neighbors : int
        k, in 1..n - 1 (see :func:`neighbourhood_size`).

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
    order = spatial_order(points)
    neighbor_index = np.empty((n, k + 1), dtype=np.uint32)
    kth_distance = np.empty(n)
    for rows in ordered_chunks(order, n, QUERY_CHUNK):
        if _cancelled is not None and _cancelled.is_set():
            return None
        distance, neighbor_index[rows] = tree.query(points[rows], k=k + 1)
        kth_distance[rows] = distance[:, k]
    return Neighbourhoods(tree, neighbor_index, kth_distance, order)


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
        self._cancelled = threading.Event()
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
                result = nearest_neighbourhoods(points, n_neighbors, self._cancelled)
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
