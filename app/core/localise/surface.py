"""Each cloud's local surface: a plane fitted to every point's neighbourhood, its spacing, noise.

One k-nearest-neighbour query per cloud (:mod:`app.core.localise.neighbourhoods`) gives, for
every point, a plane fitted to its neighbourhood (centroid and normal), the local point
spacing ``s`` (the side of the area each point stands for, from the k-th neighbour distance)
and the fit's residual.  Neighbourhoods that are a line (one scan ring on a floor seen at a
grazing angle, where rings are far apart) are refitted with three times more neighbours.  The
median residual, corrected for the fit's degrees of freedom, is the cloud's noise ``sigma``.
"""

from __future__ import annotations

import dataclasses
import importlib
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.localise.neighbourhoods import (
    Neighbourhoods,
    NeighbourhoodSearch,
    Surfaces,
    nearest_neighbourhoods,
)
from app.core.localise.settings import CHUNK
from app.core.spatial_order import ordered_chunks
from app.core.threads import for_each_chunk


def _compiled_kernel() -> Any:
    """The compiled module, or None when setup.py found no C compiler to build it.

    Imported by name: it is a leaf module, but ``from app.core.localise import ...`` would read
    as an import of this package's ``__init__``, a cycle, to tests/test_import_graph.py."""
    try:
        return importlib.import_module("app.core.localise._plane_kernel")
    except ImportError:  # pragma: no cover - depends on the install
        return None


PLANE_KERNEL: Any = _compiled_kernel()
"""The compiled plane fit (``_plane_kernel.c``), or None when it was not built: then
:func:`neighbourhood_planes` and the spacing means run as numpy passes, to the same bits."""

__all__ = [
    "PLANE_KERNEL",
    "LocalGeometry",
    "fit_surfaces",
    "local_geometry",
    "neighbourhood_planes",
    "plane_fit",
    "principal_axes",
    "weighted_plane",
    "with_surfaces",
]

LINEAR_EIGENVALUE_RATIO = 0.1
"""A neighbourhood whose middle/largest eigenvalue ratio is below this is a line, not a plane."""
LINEAR_REFIT_FACTOR = 3
"""Linear neighbourhoods are refitted with this many times more neighbours."""
SCATTER_REGULARISER = 1e-12
"""Added (times the identity) to a weighted scatter before :func:`weighted_plane` decomposes it."""
_RELEASED_INDEX = np.empty((0, 0), dtype=np.uint32)
"""Stands for a geometry's neighbour index once the localiser no longer needs it."""
_RELEASED_VARIATION = np.empty(0)
"""Stands for a geometry's ``variation`` once released with the neighbour index."""


@dataclass(frozen=True)
class LocalGeometry:
    """A cloud's KD-tree and per-point local surface (surfel) estimates.

    Attributes
    ----------
    points : ndarray, shape (n, 3), float64
    tree : pykdtree.kdtree.KDTree
        Over ``points``.
    neighbor_index : ndarray, shape (n, k + 1), uint32
        Column 0 is the point itself; empty once released (:meth:`without_neighbour_index`).
    normal : ndarray, shape (n, 3), float32
        Unit normal of the fitted plane.
    plane_constant : ndarray, shape (n,), float64
        ``normal . centroid``: the plane is ``x . normal = plane_constant``.
    spacing : ndarray, shape (n,), float64
        Local point spacing.
    noise : float
        Plane-fit residual standard deviation of the cloud.
    linear : ndarray, shape (n,), bool
        The neighbourhood is a line even when widened: no normal.
    variation : ndarray, shape (n,), float64
        Smallest eigenvalue over the trace: 0 flat, 1/3 isotropic; empty once released with
        the neighbour index.
    order : ndarray, shape (n,), intp, or None
        The cloud's :func:`~app.core.spatial_order.spatial_order` (None: file order), for
        passes that visit it a chunk of nearby points at a time.
    kernel_tree : object or None
        The compiled k-NN's tree of ``points`` (:attr:`Neighbourhoods.kernel_tree`), for the
        nearest points of the other cloud; None without it or once released.
    """

    points: NDArray[np.float64]
    tree: KDTree
    neighbor_index: NDArray[np.uint32]
    normal: NDArray[np.float32]
    plane_constant: NDArray[np.float64]
    spacing: NDArray[np.float64]
    noise: float
    linear: NDArray[np.bool_]
    variation: NDArray[np.float64]
    order: NDArray[np.intp] | None = None
    kernel_tree: Any = None

    def flattest_neighbour(self, index: NDArray[np.int64], threads: int = 1) -> NDArray[np.int64]:
        """For each point in ``index``, the neighbour (or itself) whose fit is flattest.

        Near an edge a point's own neighbourhood straddles two faces and its normal is tilted;
        the neighbour with the flattest neighbourhood lies on one face and has that face's
        normal.  Returns indices into the cloud, shape (len(index),), found :data:`CHUNK`
        points at a time on up to ``threads`` threads (each its own rows: the same answer).
        """
        flattest = np.empty(index.shape[0], dtype=self.neighbor_index.dtype)

        def find(start: int) -> None:
            neighbours = self.neighbor_index[index[start : start + CHUNK]]
            best = np.argmin(self.variation[neighbours], axis=1)
            flattest[start : start + CHUNK] = neighbours[np.arange(neighbours.shape[0]), best]

        for_each_chunk(find, range(0, index.shape[0], CHUNK), threads)
        return flattest

    def without_neighbour_index(self) -> LocalGeometry:
        """This geometry with its neighbour index (4 (k + 1) bytes a point) released, and
        ``variation`` (8 bytes a point), which only :meth:`flattest_neighbour` reads, and its
        kernel tree (28 bytes a point)."""
        return dataclasses.replace(
            self, neighbor_index=_RELEASED_INDEX, variation=_RELEASED_VARIATION, kernel_tree=None
        )


def principal_axes(
    points: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The plane fitted to one set of points: their principal axes.

    Parameters
    ----------
    points : ndarray, shape (n, 3)

    Returns
    -------
    centred : ndarray, shape (n, 3)
        The points less their mean.
    variances : ndarray, shape (3,)
        The variance along each axis, smallest first (the thinnest axis's is the plane's
        thickness squared).
    axes : ndarray, shape (3, 3)
        The axes as columns in the same order: ``axes[:, 0]`` is the plane's normal,
        ``axes[:, 1:]`` span the plane.
    """
    centred = points - points.mean(axis=0)
    scatter, axes = np.linalg.eigh(centred.T @ centred)
    return centred, scatter / max(points.shape[0], 1), axes


def plane_fit(
    c00: NDArray[np.float64],
    c11: NDArray[np.float64],
    c22: NDArray[np.float64],
    c01: NDArray[np.float64],
    c02: NDArray[np.float64],
    c12: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Eigenvalues and the smallest eigenvector of symmetric 3x3 matrices, closed form.

    Parameters
    ----------
    c00, c11, c22, c01, c02, c12 : ndarray, shape (n,)
        The six distinct entries of each matrix (elementwise arrays: no (n, 3, 3) stack).

    Returns
    -------
    smallest, largest : ndarray, shape (n,)
        Smallest (clipped at 0) and largest eigenvalue.
    normal : ndarray, shape (n, 3)
        Unit eigenvector of the smallest eigenvalue; (0, 0, 1) where the matrix is isotropic.
    """
    mean_diagonal = (c00 + c11 + c22) / 3.0
    d00, d11, d22 = c00 - mean_diagonal, c11 - mean_diagonal, c22 - mean_diagonal
    spread = np.sqrt((d00**2 + d11**2 + d22**2) / 6.0 + (c01**2 + c02**2 + c12**2) / 3.0)
    safe_spread = np.where(spread > 0, spread, 1.0)
    b00, b11, b22 = d00 / safe_spread, d11 / safe_spread, d22 / safe_spread
    b01, b02, b12 = c01 / safe_spread, c02 / safe_spread, c12 / safe_spread
    half_determinant = (
        b00 * (b11 * b22 - b12 * b12)
        - b01 * (b01 * b22 - b12 * b02)
        + b02 * (b01 * b12 - b11 * b02)
    ) / 2.0
    angle = np.arccos(np.clip(half_determinant, -1.0, 1.0)) / 3.0
    largest = mean_diagonal + 2.0 * spread * np.cos(angle)
    smallest = mean_diagonal + 2.0 * spread * np.cos(angle + 2.0 * np.pi / 3.0)
    # rows of (C - smallest I); the eigenvector is along the largest cross product of two rows
    s00, s11, s22 = c00 - smallest, c11 - smallest, c22 - smallest
    candidates = (
        (c01 * c12 - c02 * s11, c02 * c01 - s00 * c12, s00 * s11 - c01 * c01),  # row0 x row1
        (c01 * s22 - c02 * c12, c02 * c02 - s00 * s22, s00 * c12 - c01 * c02),  # row0 x row2
        (s11 * s22 - c12 * c12, c12 * c02 - c01 * s22, c01 * c12 - s11 * c02),  # row1 x row2
    )
    normal = np.empty((c00.shape[0], 3))
    best_norm_squared = np.full(c00.shape[0], -1.0)
    for x, y, z in candidates:
        norm_squared = x * x + y * y + z * z
        better = norm_squared > best_norm_squared
        normal[better] = np.stack([x[better], y[better], z[better]], axis=1)
        best_norm_squared = np.where(better, norm_squared, best_norm_squared)
    best_norm = np.sqrt(best_norm_squared)
    normal /= np.where(best_norm > 0, best_norm, 1.0)[:, None]
    normal[(best_norm <= 0) | (spread <= 0)] = (0.0, 0.0, 1.0)
    return np.maximum(smallest, 0.0), largest, normal


def weighted_plane(
    positions: NDArray[np.float64], weight: NDArray[np.floating]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The plane of each weighted set of points: their weighted centroid and the eigenvalues
    and eigenvectors of their weighted scatter about it.

    The weights are normalised per set, so the scatter is a weighted covariance whatever their
    scale; a tiny multiple of the identity (:data:`SCATTER_REGULARISER`) is added before the
    decomposition, which leaves the eigenvectors as they are and keeps an empty or degenerate
    set's finite.

    Parameters
    ----------
    positions : ndarray, shape (b, k, 3)
    weight : ndarray, shape (b, k)
        Non-negative; 0 leaves a point out.  A set whose weights are all 0 gets the origin as
        its centroid.

    Returns
    -------
    centroid : ndarray, shape (b, 3)
    values : ndarray, shape (b, 3)
        Eigenvalues of the weighted scatter, ascending.
    vectors : ndarray, shape (b, 3, 3)
        The matching unit eigenvectors as columns: ``vectors[:, :, 0]`` is the plane's normal.
    """
    total = weight.sum(axis=1)
    share = weight / np.where(total > 0, total, 1.0)[:, None]
    centroid = np.einsum("bk,bkd->bd", share, positions)
    centred = positions - centroid[:, None, :]
    # a batched matrix product: a three-operand einsum takes numpy's generic loop (4-5x slower)
    scatter = np.matmul((share[:, :, None] * centred).transpose(0, 2, 1), centred)
    values, vectors = np.linalg.eigh(scatter + SCATTER_REGULARISER * np.eye(3))
    return centroid, values, vectors


def neighbourhood_planes(
    points: NDArray[np.float64],
    neighbor_index: NDArray[np.integer],
    order: NDArray[np.intp] | None = None,
    threads: int = 1,
) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray]:
    """Plane (normal and constant) and eigenvalues of each neighbourhood.

    Each coordinate is gathered separately (from a strided column view of ``points``, which
    saves the contiguous copy's 8 bytes a point) into a contiguous (chunk, k) array, so the
    covariance is six contiguous dot products per neighbourhood, faster than products of
    strided slices of a (chunk, k, 3) gather (figures in ``docs/performance.md``).

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    neighbor_index : ndarray, shape (p, k)
    order : ndarray, shape (p,), intp, optional
        A permutation of the rows (:func:`~app.core.spatial_order.spatial_order`): chunks of
        nearby points gather from nearby memory.  Each row's result is the same in any order.
    threads : int
        Chunks fitted at once (:func:`~app.core.threads.for_each_chunk`); the same result.

    Returns
    -------
    normal : ndarray, shape (p, 3), float32
        Unit normal of the plane through the neighbourhood's centroid.
    plane_constant : ndarray, shape (p,), float64
        ``centroid . normal`` with the float32 normal, so that ``x . normal - plane_constant``
        is ``(x - centroid) . normal`` to float64 precision wherever ``x`` is.
    residual_variance : ndarray, shape (p,)
        Smallest eigenvalue (mean squared distance to the plane).
    middle_over_largest : ndarray, shape (p,)
        Middle over largest eigenvalue: ~0 for points along a line (one scan ring).
    variation : ndarray, shape (p,)
        Smallest eigenvalue over the trace (surface variation): 0 on a plane.
    """
    count, k = neighbor_index.shape
    normal = np.empty((count, 3), dtype=np.float32)
    plane_constant = np.empty(count)
    residual_variance = np.empty(count)
    middle_over_largest = np.empty(count)
    variation = np.empty(count)
    outputs = (normal, plane_constant, residual_variance, middle_over_largest, variation)
    kernel = PLANE_KERNEL if _kernel_reads(points, neighbor_index) else None

    def fit(chunk: NDArray[np.intp] | slice) -> None:
        if kernel is not None:
            _compiled_fit(kernel, points, neighbor_index, _row_numbers(chunk, count), outputs)
            return
        index = neighbor_index[chunk]
        centroid = np.empty((index.shape[0], 3))
        deviation = []
        for axis in range(3):
            values = points[:, axis][index]  # (c, k)
            mean = values.mean(axis=1)
            centroid[:, axis] = mean
            values -= mean[:, None]
            deviation.append(values)
        dx, dy, dz = deviation
        c00, c11, c22, c01, c02, c12 = (
            np.einsum("ck,ck->c", first, second) / k
            for first, second in ((dx, dx), (dy, dy), (dz, dz), (dx, dy), (dx, dz), (dy, dz))
        )
        smallest, largest, normal[chunk] = plane_fit(c00, c11, c22, c01, c02, c12)
        plane_constant[chunk] = np.einsum("cd,cd->c", centroid, normal[chunk].astype(np.float64))
        trace = c00 + c11 + c22
        middle = trace - smallest - largest
        middle_over_largest[chunk] = middle / np.maximum(largest, 1e-300)
        variation[chunk] = smallest / np.maximum(trace, 1e-300)
        residual_variance[chunk] = smallest

    for_each_chunk(fit, ordered_chunks(order, count, CHUNK), threads)
    return normal, plane_constant, residual_variance, middle_over_largest, variation


def _kernel_reads(values: NDArray, neighbor_index: NDArray) -> bool:
    """Whether the compiled kernel is there and takes these arrays (float64 values, a C-order
    uint32 index: what the localiser's KD-tree queries give); the numpy passes otherwise."""
    return (
        PLANE_KERNEL is not None
        and values.dtype == np.float64
        and neighbor_index.dtype == np.uint32
        and neighbor_index.flags.c_contiguous
    )


def _row_numbers(chunk: NDArray[np.intp] | slice, count: int) -> NDArray[np.int64]:
    """The rows a chunk of :func:`~app.core.spatial_order.ordered_chunks` selects, shape (c,)."""
    if isinstance(chunk, slice):
        return np.arange(*chunk.indices(count), dtype=np.int64)
    return np.ascontiguousarray(chunk, dtype=np.int64)


def _compiled_fit(
    kernel: Any,
    points: NDArray[np.float64],
    neighbor_index: NDArray[np.uint32],
    rows: NDArray[np.int64],
    outputs: tuple[NDArray, NDArray, NDArray, NDArray, NDArray],
) -> None:
    """:func:`neighbourhood_planes`' fit of ``rows`` (c,) by the compiled kernel, written to
    ``outputs`` (normal (p, 3) float32, then the four (p,) float64 arrays) at those rows.

    The kernel's first loop gathers each neighbourhood and stops at :func:`plane_fit`'s arccos;
    the arccos and cosines are numpy's (as in :func:`plane_fit`: its vectorised versions differ
    from the C library's in the last bits); its second loop does the rest.  The same bits as
    the numpy passes (``tests/core/test_plane_kernel.py``)."""
    moments = np.empty((12, rows.shape[0]))  # 6 covariances, centroid, mean, spread, det / 2
    kernel.plane_moments(points, neighbor_index, rows, moments)
    angle = np.arccos(np.clip(moments[11], -1.0, 1.0)) / 3.0
    largest_cosine = np.cos(angle)
    smallest_cosine = np.cos(angle + 2.0 * np.pi / 3.0)
    kernel.plane_finish(moments, largest_cosine, smallest_cosine, rows, *outputs)


def fit_surfaces(
    points: NDArray[np.float64],
    tree: KDTree,
    neighbor_index: NDArray[np.uint32],
    kth_distance: NDArray[np.float64],
    order: NDArray[np.intp] | None = None,
    threads: int = 1,
) -> Surfaces:
    """Fit a plane to every point's neighbourhood; estimate spacing and noise.

    Neighbourhoods that are nearly a line (the k nearest points all on one scan ring, as on
    floors and walls seen at grazing angles, where rings are far apart) do not define a plane:
    those are refitted with :data:`LINEAR_REFIT_FACTOR` times more neighbours.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    tree : pykdtree.kdtree.KDTree
        Over ``points``.
    neighbor_index : ndarray, shape (n, k + 1), uint32
    kth_distance : ndarray, shape (n,)
    order : ndarray, shape (n,), intp, optional
        The cloud's spatial order (:class:`Neighbourhoods`).
    threads : int
        Chunks of the per-point passes worked on at once (the same result).

    Returns
    -------
    Surfaces
    """
    n = points.shape[0]
    k = neighbor_index.shape[1] - 1
    normal, plane_constant, residual_variance, middle_over_largest, variation = (
        neighbourhood_planes(points, neighbor_index, order, threads)
    )
    is_linear = middle_over_largest < LINEAR_EIGENVALUE_RATIO
    del middle_over_largest
    # side of the area each point stands for: k points in a disc of radius r_k (a new array:
    # ``kth_distance`` may be the caller's, and is left as it was)
    raw_spacing = kth_distance * math.sqrt(math.pi / k)
    # plane fit of k+1 points has k+1-3 residual degrees of freedom
    residual_variance *= (k + 1) / max(k + 1 - 3, 1)
    # the linear points in spatial order, so that their query and gathers stay local
    linear = np.flatnonzero(is_linear) if order is None else order[is_linear[order]]
    k_wide = min(LINEAR_REFIT_FACTOR * k, n - 1)
    if linear.size and k_wide > k:
        wide_distance, wide_index = tree.query(points[linear], k=k_wide + 1)
        (
            normal[linear],
            plane_constant[linear],
            wide_residual,
            wide_middle_over_largest,
            variation[linear],
        ) = neighbourhood_planes(points, wide_index)
        is_linear[linear] = wide_middle_over_largest < LINEAR_EIGENVALUE_RATIO
        residual_variance[linear] = wide_residual * (k_wide + 1) / (k_wide + 1 - 3)
        raw_spacing[linear] = wide_distance[:, k_wide] * math.sqrt(math.pi / k_wide)
    spacing = _neighbourhood_means(raw_spacing, neighbor_index, order, threads)
    del raw_spacing
    np.maximum(spacing, 1e-12, out=spacing)
    noise = float(np.sqrt(np.median(residual_variance)))
    return Surfaces(normal, plane_constant, spacing, noise, is_linear, variation)


def _neighbourhood_means(
    values: NDArray[np.float64],
    neighbor_index: NDArray[np.uint32],
    order: NDArray[np.intp] | None,
    threads: int,
) -> NDArray[np.float64]:
    """The mean of ``values`` (n,) over each point's neighbourhood (n, k + 1), shape (n,)."""
    count = neighbor_index.shape[0]
    means = np.empty(count)
    kernel = (
        PLANE_KERNEL
        if _kernel_reads(values, neighbor_index) and values.flags.c_contiguous
        else None
    )

    def mean(chunk: NDArray[np.intp] | slice) -> None:
        if kernel is not None:
            kernel.neighbourhood_means(values, neighbor_index, _row_numbers(chunk, count), means)
        else:
            means[chunk] = values[neighbor_index[chunk]].mean(axis=1)

    for_each_chunk(mean, ordered_chunks(order, neighbor_index.shape[0], CHUNK), threads)
    return means


def with_surfaces(points: NDArray[np.float64], neighbourhoods: Neighbourhoods) -> Neighbourhoods:
    """``neighbourhoods`` with their :func:`fit_surfaces` (as they are if fitted already)."""
    if neighbourhoods.surfaces is not None:
        return neighbourhoods
    surfaces = fit_surfaces(
        points,
        neighbourhoods.tree,
        neighbourhoods.neighbor_index,
        neighbourhoods.kth_distance,
        neighbourhoods.order,
    )
    return dataclasses.replace(neighbourhoods, surfaces=surfaces)


def local_geometry(
    points: NDArray[np.float64],
    n_neighbors: int,
    *,
    neighbourhoods: Neighbourhoods | NeighbourhoodSearch | None = None,
    threads: int = 1,
) -> LocalGeometry:
    """Each point's neighbourhood and local surface (:func:`fit_surfaces`).

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    n_neighbors : int
        Neighbours besides the point itself (reduced to n - 1 for tiny clouds).
    neighbourhoods : Neighbourhoods or NeighbourhoodSearch, optional
        Of ``points``, computed ahead (with their surfaces, or not); found here otherwise.
    threads : int
        Threads of the surface fits (:func:`fit_surfaces`; the same result).

    Returns
    -------
    LocalGeometry

    Raises
    ------
    ValueError
        ``neighbourhoods`` were computed for another cloud or k.
    """
    n = points.shape[0]
    k = min(n_neighbors, n - 1)
    if isinstance(neighbourhoods, NeighbourhoodSearch):
        neighbourhoods = neighbourhoods.take()
    if neighbourhoods is None:
        neighbourhoods = nearest_neighbourhoods(points, k)
    elif neighbourhoods.neighbor_index.shape != (n, k + 1):
        raise ValueError(
            f"neighbourhoods of shape {neighbourhoods.neighbor_index.shape} were computed for "
            f"another cloud or k; this cloud needs {(n, k + 1)}"
        )
    tree, neighbor_index, order, kernel_tree = (
        neighbourhoods.tree,
        neighbourhoods.neighbor_index,
        neighbourhoods.order,
        neighbourhoods.kernel_tree,
    )
    surfaces = neighbourhoods.surfaces
    if surfaces is None:
        kth_distance = neighbourhoods.kth_distance
        del neighbourhoods  # its k-th distances go once the spacing is made from them
        surfaces = fit_surfaces(points, tree, neighbor_index, kth_distance, order, threads)
    return LocalGeometry(
        points=points,
        tree=tree,
        neighbor_index=neighbor_index,
        normal=surfaces.normal,
        plane_constant=surfaces.plane_constant,
        spacing=surfaces.spacing,
        noise=surfaces.noise,
        linear=surfaces.linear,
        variation=surfaces.variation,
        order=order,
        kernel_tree=kernel_tree,
    )
