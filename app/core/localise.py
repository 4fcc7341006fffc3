"""Per-point change labels and changed regions between a reference scan and an aligned rescan.

The paper's scores say *whether* a site changed; this module says *where*.  Real rescans are
independent samplings at different densities from a moved sensor, with occlusions and sparse far
surfaces, so plain cloud-to-cloud nearest-neighbour distances with one global threshold flood
with false alarms.  Instead (method, reasons and measured numbers in ``docs/localisation.md``):

1. **Local geometry of each cloud.**  One k-nearest-neighbour query per cloud gives, for every
   point, a plane fitted to its neighbourhood (centroid and normal), the local point spacing
   ``s`` (the side of the area each point stands for, from the k-th neighbour distance) and the
   fit's residual.  Neighbourhoods that are a line (one scan ring on a floor seen at a grazing
   angle, where rings are far apart) are refitted with three times more neighbours.  The
   median residual, corrected for the fit's degrees of freedom, is the cloud's noise ``sigma``.
2. **Distance to the other cloud's surface** (C2M/M3C2-like).  Each neighbour ``q`` (in the
   other cloud, around the point's nearest point there) stands for a disc of radius
   ``r(q) = max(f * s(q), tau)`` on its fitted plane.  The distance of ``p`` is the smallest
   point-to-plane distance to the discs ``p`` projects into, or its nearest-point distance
   when it projects into none (the other cloud has no surface there).  A matched point (its
   nearest point's disc contains it: never a candidate) gets that one plane's offset.
3. **Change candidates.**  ``p`` is a candidate when that distance exceeds
   ``tau = threshold_factor * sqrt(sigma_ref^2 + sigma_scan^2 + registration_rmse^2)`` AND no
   point of the other cloud lies within ``r`` of it: the threshold along the normal follows
   the measured noise, the one across the surface the other cloud's local spacing.  The
   support factor ``f`` is calibrated on the data: how far, in local spacings, a point's
   nearest neighbour in the other cloud typically is (~1.3 for independent lidar samplings;
   ~0.6 for the paper's corridor, whose two clouds are the same points with fresh noise).
4. **Visibility: unobserved is never change.**  With the other cloud's sensor origin, its
   returns are indexed by direction from that origin (a KD-tree on unit vectors: a spherical
   range image that adapts to any ray pattern).  For each candidate, the returns within a few
   angular steps of its direction are compared with where each ray meets the candidate's own
   surface (its plane): a return clearly short of the candidate (or of that crossing) means it
   was occluded; no return means out of range or field of view; both give *unobserved*.  Rays
   that cross the candidate's plane near it, where its own cloud has surface, and carry on
   clearly beyond it saw free space there: *changed*.  Rays that end there: the surface is
   there after all, *unchanged*.  A candidate whose surface the other sensor saw only edge-on
   gets no evidence of its own; it is changed when connected to candidates mostly seen through
   (a removed box's side face), unobserved otherwise.  Without an origin, a coverage test: a
   candidate whose nearest point in the other cloud is farther than ``coverage_factor`` local
   spacings is unobserved (that is right for merged multi-view maps; single-viewpoint scans
   should pass origins, or their shadows' rims come out as changes).
5. **Regions.**  Changed points of each cloud are linked to neighbours closer than
   ``cluster_factor`` local spacings (k-nearest-neighbour graph, sparse connected
   components); clusters smaller than ``min_region_points`` are noise and relabelled
   unchanged, so the changed points are exactly the regions' points.

Everything is vectorised numpy with pykdtree's k-NN; the reference and scan sides run on two
threads when available: a 1M x 1M pair takes 6.5-8 s on 2 cores (``docs/performance.md``).
"""

from __future__ import annotations

import dataclasses
import math
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from threadpoolctl import threadpool_limits

from app.core.cloud import MIN_POINTS
from app.core.errors import InputError, PointCloudError
from app.core.threads import available_threads

__all__ = [
    "DEFAULT_PARAMETERS",
    "LABEL_CHANGED",
    "LABEL_UNCHANGED",
    "LABEL_UNOBSERVED",
    "ChangedRegion",
    "Localisation",
    "NeighbourhoodSearch",
    "Neighbourhoods",
    "localise_changes",
    "nearest_neighbourhoods",
    "neighbourhood_size",
    "start_neighbourhood_search",
]

LABEL_UNCHANGED = 0
LABEL_CHANGED = 1
LABEL_UNOBSERVED = -1

DEFAULT_PARAMETERS: dict[str, Any] = {
    "n_neighbors": 10,
    "threshold_factor": 3.5,
    "support_factor": None,
    "cluster_factor": 2.5,
    "coverage_factor": 10.0,
    "visibility_margin_factor": 1.0,
    "visibility_angle_factor": 2.5,
    "visibility_beyond_fraction": 0.5,
    "visibility_miss_factor": 4.0,
}
"""Keyword parameters of :func:`localise_changes` and their defaults.

n_neighbors
    Neighbours (besides the point) of the local plane fit, spacing and noise estimate.  10
    spans two rings of a lidar whose rings are twice as far apart as its columns; line-shaped
    neighbourhoods are refitted with 3x more anyway.
threshold_factor
    ``tau`` in standard deviations of the combined noise (3.5: ~1 in 2000 two-sided under
    Gaussian noise; the minimum over neighbouring discs makes false candidates rarer still).
support_factor
    Support radius in the other cloud's local spacings; None calibrates it (3.5 x the lower
    quartile of nearest-neighbour distances in local spacings, clipped to [0.5, 2]).
cluster_factor
    Changed points closer than this many local spacings belong to one region.
coverage_factor
    Without the other sensor's origin: a candidate farther than this many of the other
    cloud's local spacings from it is unobserved.  Without a viewpoint a removed object and
    a hole in the other cloud's coverage look alike: larger values find more of large changes
    and flag more rims of holes (shadows).  Single-viewpoint scans should pass origins.
visibility_margin_factor
    Scales the range margin that makes a return "clearly" before or beyond a candidate:
    ``sqrt((t_own / cos(incidence))^2 + t_other^2)`` with ``t = threshold_factor * sigma``.
visibility_angle_factor
    Returns within this many typical angular steps of the candidate's direction are the
    other sensor's view of it (at most 8 returns are used).
visibility_beyond_fraction
    Fraction of the rays crossing the candidate's surface near it that must pass beyond it.
visibility_miss_factor
    "Near": within ``max(miss_factor * own spacing, candidate's distance)`` of the candidate.
"""

SUPPORT_FACTOR_QUANTILE = 0.25
SUPPORT_FACTOR_PER_QUANTILE = 3.5
"""Calibrated support factor = 3.5 x the lower quartile of nearest-neighbour distances in local
spacings (~1.3 for independent lidar samplings; the quartile ignores up to 75 % of points
being changed or unobserved)."""
SUPPORT_FACTOR_RANGE = (0.5, 2.0)
MIN_REGION_POINTS_FLOOR = 4
"""Smallest default minimum region size: 1-3 point clusters are noise."""
MIN_REGION_POINTS_PER_SQRT = 0.08
"""Default minimum region size = max(4, 0.08 sqrt(min(n, m))): 4 for the 300-point corridor,
11 at 20k, 18 at 50k, 36 at 200k points.  Spurious clusters come from one-dimensional features
at the resolution limit (an edge, a thin strip seen at a grazing angle) whose point count grows
like sqrt(n); an object's grows like n, so it stays far above this."""
RESOLUTION_THRESHOLD_FRACTION = 0.05
"""``tau`` is at least this fraction of the median spacing (noise-free data has sigma = 0)."""
MIN_INCIDENCE_COSINE = math.cos(math.radians(85.0))
"""Rays meeting a candidate's plane at more than 85 degrees incidence graze it: no evidence."""
STATUS_SURFACE = 0
STATUS_SEEN_THROUGH = 1
STATUS_UNOBSERVED = -1
STATUS_EDGE_ON = 2
"""Visibility of a change candidate: the other sensor saw a surface where it is (unchanged),
saw free space through it (changed), could not see it (unobserved), or saw its surface only
edge-on (changed if most of its connected candidates were seen through, else unobserved)."""
EDGE_ON_SEEN_THROUGH_SHARE = 0.5
LINEAR_EIGENVALUE_RATIO = 0.1
"""A neighbourhood whose middle/largest eigenvalue ratio is below this is a line, not a plane."""
LINEAR_REFIT_FACTOR = 3
"""Linear neighbourhoods are refitted with this many times more neighbours."""
OWN_SUPPORT_FACTOR = 0.75
"""A ray's crossing of a candidate's plane is evidence only within this many own spacings of
an own point (stricter than the support radius: only evidence is lost, never invented)."""
CLUSTER_NEIGHBOURS = 10
VISIBILITY_RAYS = 8
_CHUNK = 32_768
_QUERY_CHUNK = 65_536
_RELEASED_INDEX = np.empty((0, 0), dtype=np.uint32)
"""Stands for a geometry's neighbour index once the localiser no longer needs it."""
_GATHER_CHUNK = 16_384
"""Points per step of (chunk, neighbours, 3) gathers: a few MB per temporary array."""
_ANGULAR_SAMPLE = 4096
_ALIGNMENT_SAMPLE = 20_000


@dataclass(frozen=True)
class ChangedRegion:
    """One connected cluster of changed points.

    Attributes
    ----------
    kind : {"added", "removed"}
        "added": scan points with no counterpart in the reference; "removed": reference points
        with no counterpart in the scan.
    point_indices : ndarray, shape (k,), int64
        Sorted indices into the scan ("added") or the reference ("removed").
    centroid, bbox_min, bbox_max : ndarray, shape (3,), float64
        Mean position and axis-aligned bounds of the points, in the reference frame.
    mean_distance, max_distance : float
        Mean and largest distance of the points to the other cloud's surface (metres).
    """

    kind: str
    point_indices: NDArray[np.int64]
    centroid: NDArray[np.float64]
    bbox_min: NDArray[np.float64]
    bbox_max: NDArray[np.float64]
    mean_distance: float
    max_distance: float

    @property
    def n_points(self) -> int:
        """Number of points in the region."""
        return int(self.point_indices.shape[0])


@dataclass(frozen=True)
class Localisation:
    """Per-point labels, distances and regions of one comparison.

    Attributes
    ----------
    reference_label : ndarray, shape (n,), int8
        0 unchanged, 1 changed ("removed"), -1 unobserved (the scan could not see it).
    scan_label : ndarray, shape (m,), int8
        0 unchanged, 1 changed ("added"), -1 unobserved (the reference could not see it).
    reference_distance : ndarray, shape (n,), float32
        Distance (metres) to the scan's surface; NaN where unobserved.
    scan_distance : ndarray, shape (m,), float32
        Distance to the reference's surface; NaN where unobserved.
    reference_region : ndarray, shape (n,), int32
        Index into ``regions`` of each reference point's region, -1 if none.
    scan_region : ndarray, shape (m,), int32
        Likewise for scan points.
    regions : list of ChangedRegion
        Sorted by ``n_points``, largest first.
    parameters : dict
        JSON-serialisable effective parameters and estimates (noise, spacing, thresholds,
        support and cluster radii, minimum region size, visibility mode, counts).
    """

    reference_label: NDArray[np.int8]
    scan_label: NDArray[np.int8]
    reference_distance: NDArray[np.float32]
    scan_distance: NDArray[np.float32]
    reference_region: NDArray[np.int32]
    scan_region: NDArray[np.int32]
    regions: list[ChangedRegion]
    parameters: dict[str, Any]


@dataclass(frozen=True)
class _LocalGeometry:
    """A cloud's KD-tree and per-point local surface (surfel) estimates."""

    points: NDArray[np.float64]  # (n, 3)
    tree: KDTree
    neighbor_index: NDArray[np.uint32]  # (n, k + 1), column 0 is the point itself
    normal: NDArray[np.float32]  # (n, 3) unit normal of the fitted plane
    plane_constant: NDArray[np.float64]  # (n,) normal . centroid: the plane is x . normal = c
    spacing: NDArray[np.float64]  # (n,) local point spacing
    noise: float  # plane-fit residual standard deviation of the cloud
    linear: NDArray[np.bool_]  # (n,) neighbourhood is a line even when widened: no normal
    variation: NDArray[np.float64]  # (n,) smallest eigenvalue / trace: 0 flat, 1/3 isotropic

    def flattest_neighbour(self, index: NDArray[np.int64]) -> NDArray[np.int64]:
        """For each point in ``index``, the neighbour (or itself) whose fit is flattest.

        Near an edge a point's own neighbourhood straddles two faces and its normal is tilted;
        the neighbour with the flattest neighbourhood lies on one face and has that face's
        normal.  Returns indices into the cloud, shape (len(index),).
        """
        neighbours = self.neighbor_index[index]
        best = np.argmin(self.variation[neighbours], axis=1)
        return neighbours[np.arange(neighbours.shape[0]), best]


def _as_points(points: NDArray, name: str) -> NDArray[np.float64]:
    array = np.asarray(points, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 3:
        raise PointCloudError(f"{name} must have shape (n, 3), got {array.shape}")
    if array.shape[0] < MIN_POINTS:
        raise PointCloudError(
            f"{name} has {array.shape[0]} points; at least {MIN_POINTS} are needed"
        )
    if not np.isfinite(array).all():
        raise PointCloudError(f"{name} contains NaN or infinite coordinates")
    return np.ascontiguousarray(array)


def _as_origin(origin: NDArray | None, name: str) -> NDArray[np.float64] | None:
    if origin is None:
        return None
    array = np.asarray(origin, dtype=np.float64).reshape(-1)
    if array.shape != (3,) or not np.isfinite(array).all():
        raise InputError(f"{name} must be 3 finite numbers, got {np.asarray(origin).tolist()}")
    return array


def _resolve_parameters(params: dict[str, Any]) -> dict[str, Any]:
    """Defaults merged with ``params``, validated; raises InputError naming the bad one."""
    unknown = sorted(set(params) - set(DEFAULT_PARAMETERS))
    if unknown:
        raise InputError(
            f"unknown localisation parameter(s) {unknown}; valid: {sorted(DEFAULT_PARAMETERS)}"
        )
    settings = {**DEFAULT_PARAMETERS, **params}
    for name, value in settings.items():
        if name == "support_factor" and value is None:
            continue
        if isinstance(value, bool) or not (
            isinstance(value, int | float) and math.isfinite(value) and value > 0
        ):
            raise InputError(f"{name} must be a positive number, got {value!r}")
        settings[name] = float(value)
    if settings["n_neighbors"] != int(settings["n_neighbors"]) or settings["n_neighbors"] < 3:
        raise InputError(f"n_neighbors must be an integer >= 3, got {params['n_neighbors']!r}")
    settings["n_neighbors"] = int(settings["n_neighbors"])
    if settings["visibility_beyond_fraction"] > 1:
        value = params["visibility_beyond_fraction"]
        raise InputError(f"visibility_beyond_fraction must be in (0, 1], got {value}")
    return settings


def _plane_fit(
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


def _neighbourhood_planes(
    points: NDArray[np.float64], neighbor_index: NDArray[np.integer]
) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray]:
    """Plane (normal and constant) and eigenvalues of each neighbourhood.

    Each coordinate is gathered separately (from a strided column view of ``points``: as
    fast as from a contiguous copy, which would cost 8 bytes a point) into a contiguous
    (chunk, k) array, so the covariance is six contiguous dot products per neighbourhood
    (2.5x faster than products of strided slices of a (chunk, k, 3) gather).

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    neighbor_index : ndarray, shape (p, k)

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
    for start in range(0, count, _CHUNK):
        chunk = slice(start, start + _CHUNK)
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
        smallest, largest, normal[chunk] = _plane_fit(c00, c11, c22, c01, c02, c12)
        plane_constant[chunk] = np.einsum("cd,cd->c", centroid, normal[chunk].astype(np.float64))
        trace = c00 + c11 + c22
        middle = trace - smallest - largest
        middle_over_largest[chunk] = middle / np.maximum(largest, 1e-300)
        variation[chunk] = smallest / np.maximum(trace, 1e-300)
        residual_variance[chunk] = smallest
    return normal, plane_constant, residual_variance, middle_over_largest, variation


@dataclass(frozen=True)
class Neighbourhoods:
    """A cloud's KD-tree and every point's nearest neighbours: the localiser's largest single
    cost (the k-NN query is ~40 % of it), which a caller may compute ahead of time, e.g. for the
    reference while the scan is still being aligned (:func:`nearest_neighbourhoods`).

    Attributes
    ----------
    tree : pykdtree.kdtree.KDTree
        Over the cloud's points.
    neighbor_index : ndarray, shape (n, k + 1), uint32
        Column 0 is the point itself.
    kth_distance : ndarray, shape (n,), float64
        Distance to the k-th neighbour.
    """

    tree: KDTree
    neighbor_index: NDArray[np.uint32]
    kth_distance: NDArray[np.float64]


def neighbourhood_size(n_points: int, **params: Any) -> int:
    """The k that :func:`localise_changes` uses for a cloud of ``n_points`` with ``params``.

    Raises
    ------
    InputError
        An unknown or invalid parameter (the message :func:`localise_changes` would give).
    """
    return min(_resolve_parameters(params)["n_neighbors"], n_points - 1)


def nearest_neighbourhoods(
    points: NDArray[np.float64], n_neighbors: int, _cancelled: threading.Event | None = None
) -> Neighbourhoods | None:
    """Build the KD-tree of ``points`` and find each point's ``n_neighbors`` nearest neighbours.

    Queried in chunks, so only the k-th distance is kept (never an (n, k + 1) float array).
    The query releases the GIL: :class:`NeighbourhoodSearch` runs this on its own thread.

    Parameters
    ----------
    points : ndarray, shape (n, 3), float64
        Finite coordinates, n >= 2 (the cloud :func:`localise_changes` will be given: the same
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
    neighbor_index = np.empty((n, k + 1), dtype=np.uint32)
    kth_distance = np.empty(n)
    for start in range(0, n, _QUERY_CHUNK):
        if _cancelled is not None and _cancelled.is_set():
            return None
        chunk = slice(start, start + _QUERY_CHUNK)
        distance, neighbor_index[chunk] = tree.query(points[chunk], k=k + 1)
        kth_distance[chunk] = distance[:, k]
    return Neighbourhoods(tree, neighbor_index, kth_distance)


class NeighbourhoodSearch:
    """:func:`nearest_neighbourhoods` of a cloud, running on its own thread from creation.

    :meth:`take` waits for it and hands the result over: the search keeps no reference, so the
    memory goes as soon as the caller lets go of it (the localiser releases the neighbour index
    half-way).  :meth:`cancel` stops it at its next chunk (~65k points) and waits.

    Parameters
    ----------
    points : ndarray, shape (n, 3), float64
        Finite coordinates; the array :func:`localise_changes` will be given.
    n_neighbors : int
        k (:func:`neighbourhood_size`).
    openmp_threads : int
        OpenMP threads of the search's own KD-tree queries (1 when it shares the machine with
        other work).
    """

    def __init__(self, points: NDArray[np.float64], n_neighbors: int, openmp_threads: int = 1):
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
            # the limit applies to this thread's own OpenMP calls only
            with threadpool_limits(limits=openmp_threads, user_api="openmp"):
                self._result = nearest_neighbourhoods(points, n_neighbors, self._cancelled)
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


def start_neighbourhood_search(reference: NDArray, **params: Any) -> NeighbourhoodSearch | None:
    """The :class:`NeighbourhoodSearch` that ``localise_changes(reference, ..., **params)`` can
    take as ``reference_neighbourhoods``, already running on one OpenMP thread.

    None when :func:`localise_changes` will reject ``reference`` or ``params`` (it then reports
    them itself) or when no thread can be started (e.g. under an address-space cap).
    """
    try:
        points = _as_points(reference, "reference")
        n_neighbors = neighbourhood_size(len(points), **params)
        return NeighbourhoodSearch(points, n_neighbors, openmp_threads=1)
    except (InputError, PointCloudError, RuntimeError):
        return None


def _local_geometry(
    points: NDArray[np.float64],
    n_neighbors: int,
    neighbourhoods: Neighbourhoods | NeighbourhoodSearch | None = None,
) -> _LocalGeometry:
    """Fit a plane to every point's neighbourhood; estimate spacing and noise.

    Neighbourhoods that are nearly a line (the k nearest points all on one scan ring, as on
    floors and walls seen at grazing angles, where rings are far apart) do not define a plane:
    those are refitted with :data:`LINEAR_REFIT_FACTOR` times more neighbours.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    n_neighbors : int
        Neighbours besides the point itself (reduced to n - 1 for tiny clouds).
    neighbourhoods : Neighbourhoods or NeighbourhoodSearch, optional
        Of ``points``, computed ahead; found here otherwise.
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
    tree, neighbor_index, kth_distance = (
        neighbourhoods.tree,
        neighbourhoods.neighbor_index,
        neighbourhoods.kth_distance,
    )
    del neighbourhoods
    normal, plane_constant, residual_variance, middle_over_largest, variation = (
        _neighbourhood_planes(points, neighbor_index)
    )
    is_linear = middle_over_largest < LINEAR_EIGENVALUE_RATIO
    del middle_over_largest
    # side of the area each point stands for: k points in a disc of radius r_k (a new array:
    # ``neighbourhoods`` may be the caller's, and is left as it was)
    raw_spacing = kth_distance * math.sqrt(math.pi / k)
    del kth_distance
    # plane fit of k+1 points has k+1-3 residual degrees of freedom
    residual_variance *= (k + 1) / max(k + 1 - 3, 1)
    linear = np.flatnonzero(is_linear)
    k_wide = min(LINEAR_REFIT_FACTOR * k, n - 1)
    if linear.size and k_wide > k:
        wide_distance, wide_index = tree.query(points[linear], k=k_wide + 1)
        (
            normal[linear],
            plane_constant[linear],
            wide_residual,
            wide_middle_over_largest,
            variation[linear],
        ) = _neighbourhood_planes(points, wide_index)
        is_linear[linear] = wide_middle_over_largest < LINEAR_EIGENVALUE_RATIO
        residual_variance[linear] = wide_residual * (k_wide + 1) / (k_wide + 1 - 3)
        raw_spacing[linear] = wide_distance[:, k_wide] * math.sqrt(math.pi / k_wide)
    spacing = np.empty(n)
    for start in range(0, n, _CHUNK):
        chunk = slice(start, start + _CHUNK)
        spacing[chunk] = raw_spacing[neighbor_index[chunk]].mean(axis=1)
    del raw_spacing
    np.maximum(spacing, 1e-12, out=spacing)
    noise = float(np.sqrt(np.median(residual_variance)))
    del residual_variance
    return _LocalGeometry(
        points,
        tree,
        neighbor_index,
        normal,
        plane_constant,
        spacing,
        noise,
        is_linear,
        variation,
    )


def _nearest_in(
    points: NDArray[np.float64], other: _LocalGeometry
) -> tuple[NDArray[np.float64], NDArray[np.uint32]]:
    """Distance to and index of each point's nearest point in ``other``, shapes (p,)."""
    return other.tree.query(points, k=1)


def _support_factor(
    nn_distance_over_spacing: NDArray[np.float64], requested: float | None
) -> float:
    if requested is not None:
        return float(requested)
    quartile = float(np.quantile(nn_distance_over_spacing, SUPPORT_FACTOR_QUANTILE))
    low, high = SUPPORT_FACTOR_RANGE
    return float(np.clip(SUPPORT_FACTOR_PER_QUANTILE * quartile, low, high))


def _surface_distance(
    points: NDArray[np.float64],
    nn_distance: NDArray[np.float64],
    nn_index: NDArray[np.integer],
    other: _LocalGeometry,
    threshold: float,
    support_factor: float,
    with_plane_offset: bool = False,
) -> tuple[NDArray[np.float64], NDArray[np.bool_], NDArray[np.float64] | None]:
    """Distance of each point to the other cloud's supported local surface.

    A point whose nearest point in the other cloud lies within that point's support radius
    (``max(support_factor * spacing, tau)``) is *matched*: the other cloud has surface right
    there, so it is never a candidate, and its distance is the offset from the plane of its
    nearest point's neighbourhood (one plane: most points are matched, and this keeps their
    cost at one gather).  An unmatched point is compared with every neighbour ``q`` of its
    nearest point (a disc of radius ``max(support_factor * s(q), tau)`` on ``q``'s plane).

    Parameters
    ----------
    points : ndarray, shape (p, 3)
    nn_distance, nn_index : ndarray, shape (p,)
        Nearest point of the other cloud.
    other : _LocalGeometry
    threshold : float
        ``tau``.
    support_factor : float
    with_plane_offset : bool
        Also return the signed offsets (for the alignment residual; 8 bytes a point).

    Returns
    -------
    distance : ndarray, shape (p,)
        Matched points: absolute offset from the nearest point's plane.  Unmatched points:
        the smallest point-to-plane distance over the neighbours of the nearest point whose
        support disc ``p`` projects into; the nearest-point distance when there is none.
    candidate : ndarray, shape (p,), bool
        Unmatched and ``distance > tau``.
    nearest_plane_offset : ndarray, shape (p,), or None
        With ``with_plane_offset``: the signed offset from the nearest point's plane for
        matched points, NaN elsewhere.
    """
    nearest_plane_offset = np.full(points.shape[0], np.nan) if with_plane_offset else None
    distance = np.empty(points.shape[0])
    candidate = np.zeros(points.shape[0], dtype=bool)
    unmatched_parts = []
    for start in range(0, points.shape[0], _CHUNK):
        chunk = slice(start, start + _CHUNK)
        nearest_support = np.maximum(support_factor * other.spacing[nn_index[chunk]], threshold)
        matched = nn_distance[chunk] <= nearest_support
        unmatched_parts.append(start + np.flatnonzero(~matched))
        rows = start + np.flatnonzero(matched)
        nearest = nn_index[rows]
        offset = (
            np.einsum("pd,pd->p", points[rows], other.normal[nearest])
            - other.plane_constant[nearest]
        )
        if nearest_plane_offset is not None:
            nearest_plane_offset[rows] = offset
        distance[rows] = np.abs(offset)
    unmatched = np.concatenate(unmatched_parts)
    for start in range(0, unmatched.shape[0], _GATHER_CHUNK):
        rows = unmatched[start : start + _GATHER_CHUNK]
        query = points[rows]
        neighbours = other.neighbor_index[nn_index[rows]]  # (c, K) around the nearest point
        normals = other.normal[neighbours]
        support_radius = np.maximum(support_factor * other.spacing[neighbours], threshold)
        offset = query[:, None, :] - other.points[neighbours]
        along_normal = np.einsum("ckd,ckd->ck", offset, normals)
        lateral_squared = np.einsum("ckd,ckd->ck", offset, offset) - along_normal**2
        supported = lateral_squared <= support_radius**2
        plane_offset = np.einsum("cd,ckd->ck", query, normals) - other.plane_constant[neighbours]
        plane_distance = np.where(supported, np.abs(plane_offset), np.inf).min(axis=1)
        distance[rows] = np.where(np.isfinite(plane_distance), plane_distance, nn_distance[rows])
        candidate[rows] = distance[rows] > threshold
    return distance, candidate, nearest_plane_offset


def _alignment_residual(
    reference_side: tuple,
    scan_side: tuple,
    threshold: float,
    support_factor: float,
) -> float:
    """Misalignment left after registration, measured on the clouds themselves (metres).

    The signed point-to-plane offsets of matched points (a subsample of each cloud against
    the other; a point is matched when its nearest point in the other cloud lies within the
    support radius, so changed points do not count) have variance
    ``sigma_own^2 + sigma_other^2 / (k + 1)`` from noise alone (the plane goes through a
    neighbourhood's centroid); a robust spread (1.4826 x MAD) beyond that is alignment error,
    which then widens ``tau`` like ``registration_rmse`` does.

    Parameters
    ----------
    reference_side, scan_side : tuple
        ``(points, nn_distance, nn_index, geometry)`` of each cloud, the nearest neighbours
        being in the other cloud.
    threshold : float
        Preliminary ``tau`` (noise and registration_rmse only).
    support_factor : float

    Returns
    -------
    float
        ``sqrt(mean over both directions of max(0, spread^2 - noise^2))``.
    """
    excess_variances = []
    for (points, nn_distance, nn_index, geometry), (*_, other) in (
        (reference_side, scan_side),
        (scan_side, reference_side),
    ):
        step = max(1, points.shape[0] // _ALIGNMENT_SAMPLE)
        sample = slice(None, None, step)
        _, _, offset = _surface_distance(
            points[sample],
            nn_distance[sample],
            nn_index[sample],
            other,
            threshold,
            support_factor,
            with_plane_offset=True,
        )
        assert offset is not None  # with_plane_offset=True
        offset = offset[np.isfinite(offset)]
        if offset.size < MIN_POINTS:
            continue
        spread = 1.4826 * float(np.median(np.abs(offset - np.median(offset))))
        other_k = other.neighbor_index.shape[1]
        noise_variance = geometry.noise**2 + other.noise**2 / other_k
        excess_variances.append(max(0.0, spread**2 - noise_variance))
    return math.sqrt(float(np.mean(excess_variances))) if excess_variances else 0.0


def _ray_visibility(
    points: NDArray[np.float64],
    normals: NDArray[np.float64],
    spacing: NDArray[np.float64],
    surface_distance: NDArray[np.float64],
    linear: NDArray[np.bool_],
    own: _LocalGeometry,
    normal_tolerance: float,
    range_tolerance: float,
    other_points: NDArray[np.float64],
    other_origin: NDArray[np.float64],
    margin_factor: float,
    angle_factor: float,
    beyond_fraction: float,
    miss_factor: float,
) -> tuple[NDArray[np.int8], float]:
    """What the other sensor saw in the direction of each point.

    The other cloud's returns are indexed by direction from its origin.  For each point, the
    returns within ``angle_factor`` typical angular steps of its direction are compared with
    where each of those rays would meet the point's own surface (the plane through the point
    with its normal): a ray that stops clearly before the point (or before meeting that plane)
    means something is in front of it; a ray that meets the plane near the point (within
    ``max(miss_factor * spacing, surface_distance)``) and carries on clearly beyond it saw
    free space where the point's surface would be.

    Parameters
    ----------
    points : ndarray, shape (p, 3)
    normals : ndarray, shape (p, 3)
        Unit normals of the points' own surface.
    spacing : ndarray, shape (p,)
        The points' own cloud's local spacing.
    surface_distance : ndarray, shape (p,)
        The points' distance to the other cloud's surface.
    linear : ndarray, shape (p,), bool
        The point's neighbourhood is a line: its normal is unknown, so it gets no evidence.
    own : _LocalGeometry
        The points' own cloud: a ray's crossing of the point's plane counts only within
        :data:`OWN_SUPPORT_FACTOR` own spacings of an own point.
    normal_tolerance : float
        How far (metres) a point may lie off its true surface: threshold_factor x its
        cloud's noise and the registration residual.
    range_tolerance : float
        threshold_factor x the other cloud's noise (the error of its ranges).
    other_points : ndarray, shape (m, 3)
        The other cloud, whose sensor was at ``other_origin``.
    other_origin : ndarray, shape (3,)
    margin_factor, angle_factor, beyond_fraction, miss_factor : float
        See :data:`DEFAULT_PARAMETERS`.

    Returns
    -------
    status : ndarray, shape (p,), int8
        1 "seen through": at least ``beyond_fraction`` of the rays meeting the point's surface
        near it pass clearly beyond it, and none stops clearly before it; -1 "unobserved": no
        return in that direction (out of range or field of view), one stops clearly before
        the point (occluded), or no ray meets the point's surface near it (seen edge-on);
        0 "surface": the rays end where the point's surface is.
    angular_step : float
        The other sensor's typical angular step (radians).
    """
    other_range, other_direction = _ranges_and_directions(other_points, other_origin)
    direction_tree = KDTree(other_direction)
    sample = np.linspace(0, other_range.shape[0] - 1, min(_ANGULAR_SAMPLE, other_range.shape[0]))
    sample_step, _ = direction_tree.query(
        np.ascontiguousarray(other_direction[sample.astype(np.int64)]), k=3
    )
    angular_step = float(np.median(sample_step[:, 2]))
    rays = _Rays(other_origin, other_range, other_direction, direction_tree)
    status = np.empty(points.shape[0], dtype=np.int8)
    for start in range(0, points.shape[0], _GATHER_CHUNK):
        chunk = slice(start, start + _GATHER_CHUNK)
        status[chunk] = _ray_status(
            points[chunk],
            normals[chunk],
            spacing[chunk],
            surface_distance[chunk],
            linear[chunk],
            own,
            rays,
            normal_tolerance,
            range_tolerance,
            margin_factor,
            angle_factor * angular_step,
            beyond_fraction,
            miss_factor,
        )
    return status, angular_step


def _ranges_and_directions(
    points: NDArray[np.float64], origin: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float32]]:
    """Range and unit direction of each return from the sensor (returns at the origin dropped).

    Computed in chunks into float32 directions (angular resolution ~1e-7 rad, far below any
    lidar's step), so the direction index costs 12 bytes a return and no (m, 3) temporary.

    Parameters
    ----------
    points : ndarray, shape (m, 3)
    origin : ndarray, shape (3,)

    Returns
    -------
    range : ndarray, shape (r,), float64
    direction : ndarray, shape (r, 3), float32
    """
    count = points.shape[0]
    ranges = np.empty(count)
    directions = np.empty((count, 3), dtype=np.float32)
    for start in range(0, count, _CHUNK):
        chunk = slice(start, start + _CHUNK)
        offset = points[chunk] - origin
        ranges[chunk] = np.sqrt(np.einsum("md,md->m", offset, offset))
        with np.errstate(divide="ignore", invalid="ignore"):
            directions[chunk] = offset / ranges[chunk, None]
    valid = ranges > 0
    if not valid.all():
        return ranges[valid], directions[valid]
    return ranges, directions


@dataclass(frozen=True)
class _Rays:
    """The other sensor's returns indexed by direction (see :func:`_ray_visibility`)."""

    origin: NDArray[np.float64]  # (3,)
    range: NDArray[np.float64]  # (m,) distance of each return from the origin
    direction: NDArray[np.float32]  # (m, 3) unit vector from the origin to each return
    tree: KDTree  # on ``direction``


def _ray_status(
    points: NDArray[np.float64],
    normals: NDArray[np.float64],
    spacing: NDArray[np.float64],
    surface_distance: NDArray[np.float64],
    linear: NDArray[np.bool_],
    own: _LocalGeometry,
    rays: _Rays,
    normal_tolerance: float,
    range_tolerance: float,
    margin_factor: float,
    max_angle: float,
    beyond_fraction: float,
    miss_factor: float,
) -> NDArray[np.int8]:
    """Visibility status of a chunk of points (the body of :func:`_ray_visibility`).

    Parameters
    ----------
    points, normals : ndarray, shape (c, 3)
    spacing, surface_distance, linear : ndarray, shape (c,)
    own : _LocalGeometry
    rays : _Rays
    normal_tolerance, range_tolerance, margin_factor, beyond_fraction, miss_factor : float
        As in :func:`_ray_visibility`.
    max_angle : float
        Returns within this angle (radians, as a chord of unit vectors) of a point's
        direction are the other sensor's view of it.

    Returns
    -------
    ndarray, shape (c,), int8
    """
    other_origin, other_range, other_direction = rays.origin, rays.range, rays.direction
    offset = points - other_origin
    point_range = np.linalg.norm(offset, axis=1)
    angle, ray = rays.tree.query(
        (offset / np.maximum(point_range, 1e-12)[:, None]).astype(np.float32),
        k=min(VISIBILITY_RAYS, other_range.shape[0]),
        distance_upper_bound=max_angle,
    )
    found = np.isfinite(angle)
    ray = np.minimum(ray, other_range.shape[0] - 1)
    ray_range = other_range[ray]
    ray_direction = other_direction[ray].astype(np.float64)  # (p, k, 3)
    normals = normals.astype(np.float64)
    # where each ray meets the plane through the point: origin + crossing * direction; rays
    # that graze the plane (or points without a normal) cannot say whether the surface is there
    ray_dot_normal = np.einsum("pkd,pd->pk", ray_direction, normals)
    grazing = (np.abs(ray_dot_normal) < MIN_INCIDENCE_COSINE) | linear[:, None]
    offset_dot_normal = np.einsum("pd,pd->p", offset, normals)
    with np.errstate(divide="ignore", invalid="ignore"):
        crossing = offset_dot_normal[:, None] / ray_dot_normal
    crosses_ahead = found & ~grazing & np.isfinite(crossing) & (crossing > 0)
    crossing = np.where(crosses_ahead, crossing, np.inf)
    crossing_point = (
        other_origin + np.where(crosses_ahead, crossing, 0.0)[..., None] * ray_direction
    )
    miss_distance = np.linalg.norm(crossing_point - points[:, None, :], axis=2)
    miss_tolerance = np.maximum(miss_factor * spacing, surface_distance)
    crosses_near = crosses_ahead & (miss_distance <= miss_tolerance[:, None])
    # a point off its surface by e lies e / cos(incidence) along the ray from the surface
    cos_incidence = np.where(grazing, 1.0, np.abs(ray_dot_normal))
    margin = margin_factor * np.sqrt((normal_tolerance / cos_incidence) ** 2 + range_tolerance**2)
    # A ray that stops clearly before both the point and its crossing occludes the point
    # whatever the test below decides (the expected stop is one of the two): such points are
    # unobserved already, and most candidates of a moved sensor are (its shadows).
    occluded_anyway = ~found.any(axis=1) | (
        found & (ray_range < np.minimum(crossing, point_range[:, None]) - margin)
    ).any(axis=1)
    # ... and only where the point's own cloud has surface: a ray crossing the plane beyond
    # the edge of a table top says nothing about the table
    near_rows, near_rays = np.nonzero(crosses_near & ~occluded_anyway[:, None])
    own_distance, own_nearest = own.tree.query(crossing_point[near_rows, near_rays], k=1)
    own_support = np.maximum(OWN_SUPPORT_FACTOR * own.spacing[own_nearest], normal_tolerance)
    crosses_near[near_rows, near_rays] = own_distance <= own_support
    expected_stop = np.where(
        crosses_near, np.minimum(crossing, point_range[:, None]), point_range[:, None]
    )
    stops_before = found & (ray_range < expected_stop - margin)
    passes_beyond = crosses_near & (ray_range > crossing + margin)
    n_near = crosses_near.sum(axis=1)
    occluded = (~found.any(axis=1)) | stops_before.any(axis=1)
    seen_through = passes_beyond.sum(axis=1) >= beyond_fraction * np.maximum(n_near, 1)
    status = np.where(seen_through, STATUS_SEEN_THROUGH, STATUS_SURFACE)
    status = np.where(n_near == 0, STATUS_EDGE_ON, status)
    return np.where(occluded, STATUS_UNOBSERVED, status).astype(np.int8)


def _resolve_edge_on(
    points: NDArray[np.float64],
    spacing: NDArray[np.float64],
    status: NDArray[np.int8],
    cluster_factor: float,
) -> NDArray[np.int8]:
    """Decide candidates whose surface the other sensor saw only edge-on.

    A removed box's face that the other sensor sees edge-on gets no ray evidence of its own,
    but the sensor saw through the rest of the box: edge-on candidates connected (within
    ``cluster_factor`` local spacings) to candidates that are mostly seen through are
    changed; the others (a pillar's face seen edge-on, the rest unchanged) are unobserved.

    Parameters
    ----------
    points : ndarray, shape (c, 3)
        The candidates.
    spacing : ndarray, shape (c,)
        Their cloud's local spacing.
    status : ndarray, shape (c,), int8
        From :func:`_ray_visibility`.
    cluster_factor : float

    Returns
    -------
    ndarray, shape (c,), int8
        ``status`` with every STATUS_EDGE_ON replaced.
    """
    edge_on = status == STATUS_EDGE_ON
    if not edge_on.any():
        return status
    involved = np.flatnonzero(edge_on | (status == STATUS_SEEN_THROUGH))
    labels = _cluster_labels(points[involved], cluster_factor * spacing[involved])
    seen_through_share = np.bincount(
        labels, weights=(status[involved] == STATUS_SEEN_THROUGH).astype(np.float64)
    ) / np.bincount(labels)
    promoted = seen_through_share[labels] >= EDGE_ON_SEEN_THROUGH_SHARE
    resolved = status.copy()
    resolved[involved] = np.where(
        edge_on[involved],
        np.where(promoted, STATUS_SEEN_THROUGH, STATUS_UNOBSERVED),
        status[involved],
    )
    return resolved


def _cluster_labels(points: NDArray[np.float64], radius: NDArray[np.float64]) -> NDArray:
    """Connected components of points linked to neighbours within their own ``radius``.

    Each point is linked to its :data:`CLUSTER_NEIGHBOURS` nearest neighbours that lie within
    its radius (a k-nearest-neighbour graph cut at the radius: on surfaces it connects what
    the full radius graph connects, at a fixed cost per point).

    Parameters
    ----------
    points : ndarray, shape (c, 3)
    radius : ndarray, shape (c,)

    Returns
    -------
    ndarray, shape (c,), int
        Component label per point.
    """
    count = points.shape[0]
    if count <= 1:
        return np.zeros(count, dtype=np.int64)
    k = min(CLUSTER_NEIGHBOURS + 1, count)
    distance, neighbour = KDTree(points).query(points, k=k, distance_upper_bound=radius.max())
    linked = distance[:, 1:] <= radius[:, None]
    rows = np.repeat(np.arange(count), k - 1)[linked.ravel()]
    columns = neighbour[:, 1:][linked]
    graph = coo_matrix((np.ones(rows.shape[0], dtype=np.int8), (rows, columns)), (count, count))
    _, labels = connected_components(graph, directed=True, connection="weak")
    return labels


def _regions(
    kind: str,
    points: NDArray[np.float64],
    changed: NDArray[np.bool_],
    spacing: NDArray[np.float64],
    distance: NDArray[np.float64],
    cluster_factor: float,
    min_region_points: int,
) -> tuple[list[ChangedRegion], int]:
    """Cluster one cloud's changed points into regions of at least ``min_region_points``.

    Returns
    -------
    regions : list of ChangedRegion
    n_dropped_clusters : int
    """
    changed_index = np.flatnonzero(changed)
    labels = _cluster_labels(points[changed_index], cluster_factor * spacing[changed_index])
    if labels.size == 0:
        return [], 0
    sizes = np.bincount(labels)
    order = np.argsort(labels, kind="stable")
    boundaries = np.flatnonzero(np.diff(labels[order])) + 1
    regions = []
    for members in np.split(changed_index[order], boundaries):
        if members.shape[0] < min_region_points:
            continue
        region_points = points[members]
        region_distance = distance[members]
        regions.append(
            ChangedRegion(
                kind=kind,
                point_indices=np.sort(members).astype(np.int64),
                centroid=region_points.mean(axis=0),
                bbox_min=region_points.min(axis=0),
                bbox_max=region_points.max(axis=0),
                mean_distance=float(region_distance.mean()),
                max_distance=float(region_distance.max()),
            )
        )
    return regions, int((sizes < min_region_points).sum())


def _label_candidates(
    side: str,
    points: NDArray[np.float64],
    geometry: _LocalGeometry,
    candidate: NDArray[np.bool_],
    flattest: NDArray[np.integer],
    distance: NDArray[np.float64],
    nn_distance: NDArray[np.float64],
    nn_index: NDArray[np.int64],
    other: _LocalGeometry,
    other_origin: NDArray[np.float64] | None,
    misalignment: float,
    settings: dict[str, Any],
) -> tuple[NDArray[np.int8], dict[str, Any]]:
    """Label one cloud's points: candidates become changed or unobserved, the rest unchanged.

    Parameters
    ----------
    side : {"reference", "scan"}
        Prefix of the report's keys.
    points : ndarray, shape (p, 3)
    geometry : _LocalGeometry
        Of ``points``.
    candidate, distance, nn_distance, nn_index : ndarray, shape (p,)
        From the comparison with the other cloud.
    flattest : ndarray, shape (c,)
        ``geometry.flattest_neighbour`` of each candidate (taken before the neighbour index
        was released).
    other : _LocalGeometry
        The other cloud.
    other_origin : ndarray, shape (3,), or None
        The other sensor's position: ray visibility test if given, coverage test otherwise.
    misalignment : float
        registration_rmse and the measured alignment residual combined (metres).
    settings : dict
        Resolved keyword parameters.

    Returns
    -------
    label : ndarray, shape (p,), int8
        LABEL_UNCHANGED, LABEL_CHANGED or LABEL_UNOBSERVED.
    report : dict
        JSON-serialisable figures of the visibility test.
    """
    label = np.full(points.shape[0], LABEL_UNCHANGED, dtype=np.int8)
    index = np.flatnonzero(candidate)
    report: dict[str, Any] = {f"{side}_candidates": int(index.size)}
    if other_origin is None:
        report[f"{side}_visibility"] = "coverage"
        covered = nn_distance[index] <= settings["coverage_factor"] * other.spacing[nn_index[index]]
        status = np.where(covered, STATUS_SEEN_THROUGH, STATUS_UNOBSERVED)
    else:
        report[f"{side}_visibility"] = "ray"
        status, angular_step = _ray_visibility(
            points[index],
            geometry.normal[flattest],
            geometry.spacing[index],
            distance[index],
            geometry.linear[flattest],
            geometry,
            settings["threshold_factor"] * math.hypot(geometry.noise, misalignment),
            settings["threshold_factor"] * other.noise,
            other.points,
            other_origin,
            settings["visibility_margin_factor"],
            settings["visibility_angle_factor"],
            settings["visibility_beyond_fraction"],
            settings["visibility_miss_factor"],
        )
        report[f"{side}_other_angular_step_deg"] = math.degrees(angular_step)
        report[f"{side}_candidates_on_other_surface"] = int((status == STATUS_SURFACE).sum())
        report[f"{side}_candidates_edge_on"] = int((status == STATUS_EDGE_ON).sum())
        status = _resolve_edge_on(
            points[index], geometry.spacing[index], status, settings["cluster_factor"]
        )
    label[index[status == STATUS_SEEN_THROUGH]] = LABEL_CHANGED
    label[index[status == STATUS_UNOBSERVED]] = LABEL_UNOBSERVED
    return label, report


def _both(
    threads: int, function: Callable[..., Any], *argument_pairs: tuple[Any, Any]
) -> tuple[Any, Any]:
    """``function`` on the reference's and the scan's arguments, concurrently if threads >= 2.

    The two sides of a comparison are independent (numpy and the KD-tree release the GIL), so
    with two threads the localiser takes about half the time; the results are the same.
    ``argument_pairs`` holds one ``(reference_argument, scan_argument)`` per parameter.
    """
    first = [pair[0] for pair in argument_pairs]
    second = [pair[1] for pair in argument_pairs]
    if threads < 2:
        return function(*first), function(*second)
    with ThreadPoolExecutor(max_workers=1) as pool:
        future = pool.submit(function, *first)
        second_result = function(*second)
        return future.result(), second_result


def localise_changes(
    reference: NDArray,
    scan: NDArray,
    *,
    reference_origin: NDArray | None = None,
    scan_origin: NDArray | None = None,
    registration_rmse: float = 0.0,
    min_region_points: int | None = None,
    threads: int | None = None,
    reference_neighbourhoods: Neighbourhoods | NeighbourhoodSearch | None = None,
    **params: Any,
) -> Localisation:
    """Label each point unchanged, changed or unobserved and group changes into regions.

    Parameters
    ----------
    reference : array_like, shape (n, 3)
        The reference scan.
    scan : array_like, shape (m, 3)
        The new scan, already aligned into the reference frame.
    reference_origin : array_like, shape (3,), optional
        The reference sensor's position (reference frame).  Enables the ray visibility test
        for scan points; without it they get the coverage test.
    scan_origin : array_like, shape (3,), optional
        The scan sensor's position, already in the reference frame.  Enables the ray
        visibility test for reference points.
    registration_rmse : float
        Residual of the alignment (metres); widens the distance threshold.
    min_region_points : int, optional
        Smaller clusters of changed points are noise and relabelled unchanged.  Default:
        ``max(4, round(0.08 * sqrt(min(n, m))))``.
    threads : int, optional
        Threads to use (the reference and scan sides run concurrently from 2; the KD-tree
        queries use OpenMP's setting).  Default: :func:`available_threads`.  The result does
        not depend on it.
    reference_neighbourhoods : Neighbourhoods or NeighbourhoodSearch, optional
        :func:`nearest_neighbourhoods` of ``reference`` with :func:`neighbourhood_size`
        neighbours, computed ahead (the pipeline starts one with
        :func:`start_neighbourhood_search` while the scan is aligned).  The result is the same
        as without it.
    **params
        See :data:`DEFAULT_PARAMETERS`.

    Returns
    -------
    Localisation

    Raises
    ------
    PointCloudError
        A cloud is not (n, 3), has non-finite values or fewer than 10 points.
    InputError
        An unknown or invalid parameter or origin.
    """
    settings = _resolve_parameters(params)
    threads = available_threads() if threads is None else max(1, int(threads))
    reference_points = _as_points(reference, "reference")
    scan_points = _as_points(scan, "scan")
    reference_origin = _as_origin(reference_origin, "reference_origin")
    scan_origin = _as_origin(scan_origin, "scan_origin")
    if not (math.isfinite(registration_rmse) and registration_rmse >= 0):
        raise InputError(f"registration_rmse must be >= 0, got {registration_rmse}")
    if min_region_points is None:
        min_region_points = max(
            MIN_REGION_POINTS_FLOOR,
            round(
                MIN_REGION_POINTS_PER_SQRT * math.sqrt(min(len(reference_points), len(scan_points)))
            ),
        )
    elif min_region_points < 1:
        raise InputError(f"min_region_points must be >= 1, got {min_region_points}")

    n_neighbors = settings["n_neighbors"]
    reference_geometry, scan_geometry = _both(
        threads,
        _local_geometry,
        (reference_points, scan_points),
        (n_neighbors, n_neighbors),
        (reference_neighbourhoods, None),
    )
    (reference_nn_distance, reference_nn_index), (scan_nn_distance, scan_nn_index) = _both(
        threads, _nearest_in, (reference_points, scan_points), (scan_geometry, reference_geometry)
    )

    median_spacing = float(
        np.median(np.concatenate([reference_geometry.spacing, scan_geometry.spacing]))
    )
    relative_nn_distance = np.concatenate(
        [
            reference_nn_distance / scan_geometry.spacing[reference_nn_index],
            scan_nn_distance / reference_geometry.spacing[scan_nn_index],
        ]
    )
    support_factor = _support_factor(relative_nn_distance, settings["support_factor"])
    nn_distance_quartile = float(np.quantile(relative_nn_distance, SUPPORT_FACTOR_QUANTILE))
    del relative_nn_distance  # 8 bytes a point of both clouds
    resolution_floor = RESOLUTION_THRESHOLD_FRACTION * median_spacing
    noise_only_threshold = max(
        settings["threshold_factor"]
        * math.hypot(reference_geometry.noise, scan_geometry.noise, registration_rmse),
        resolution_floor,
    )
    alignment_residual = _alignment_residual(
        (reference_points, reference_nn_distance, reference_nn_index, reference_geometry),
        (scan_points, scan_nn_distance, scan_nn_index, scan_geometry),
        noise_only_threshold,
        support_factor,
    )
    threshold = max(
        settings["threshold_factor"]
        * math.hypot(
            reference_geometry.noise, scan_geometry.noise, registration_rmse, alignment_residual
        ),
        resolution_floor,
    )

    (reference_distance, reference_candidate, _), (scan_distance, scan_candidate, _) = _both(
        threads,
        _surface_distance,
        (reference_points, scan_points),
        (reference_nn_distance, scan_nn_distance),
        (reference_nn_index, scan_nn_index),
        (scan_geometry, reference_geometry),
        (threshold, threshold),
        (support_factor, support_factor),
    )
    # From here on the neighbour index (4 (k + 1) bytes a point) is needed only for the
    # candidates' flattest neighbours: take those and release it before the visibility test.
    reference_flattest = reference_geometry.flattest_neighbour(np.flatnonzero(reference_candidate))
    scan_flattest = scan_geometry.flattest_neighbour(np.flatnonzero(scan_candidate))
    reference_geometry = dataclasses.replace(reference_geometry, neighbor_index=_RELEASED_INDEX)
    scan_geometry = dataclasses.replace(scan_geometry, neighbor_index=_RELEASED_INDEX)
    misalignment = math.hypot(registration_rmse, alignment_residual)
    (reference_label, reference_report), (scan_label, scan_report) = _both(
        threads,
        _label_candidates,
        ("reference", "scan"),
        (reference_points, scan_points),
        (reference_geometry, scan_geometry),
        (reference_candidate, scan_candidate),
        (reference_flattest, scan_flattest),
        (reference_distance, scan_distance),
        (reference_nn_distance, scan_nn_distance),
        (reference_nn_index, scan_nn_index),
        (scan_geometry, reference_geometry),
        (scan_origin, reference_origin),
        (misalignment, misalignment),
        (settings, settings),
    )

    factor = settings["cluster_factor"]
    (removed, dropped_removed), (added, dropped_added) = _both(
        threads,
        _regions,
        ("removed", "added"),
        (reference_points, scan_points),
        (reference_label == LABEL_CHANGED, scan_label == LABEL_CHANGED),
        (reference_geometry.spacing, scan_geometry.spacing),
        (reference_distance, scan_distance),
        (factor, factor),
        (min_region_points, min_region_points),
    )
    regions: list[ChangedRegion] = [*removed, *added]
    dropped = {"removed": dropped_removed, "added": dropped_added}
    regions.sort(key=lambda region: (-region.n_points, region.kind, int(region.point_indices[0])))

    reference_region = np.full(len(reference_points), -1, dtype=np.int32)
    scan_region = np.full(len(scan_points), -1, dtype=np.int32)
    for number, region in enumerate(regions):
        target = reference_region if region.kind == "removed" else scan_region
        target[region.point_indices] = number
    # changed points outside any kept region were in clusters too small to be a change
    reference_label[(reference_label == LABEL_CHANGED) & (reference_region < 0)] = LABEL_UNCHANGED
    scan_label[(scan_label == LABEL_CHANGED) & (scan_region < 0)] = LABEL_UNCHANGED

    reference_distance_out = reference_distance.astype(np.float32)
    reference_distance_out[reference_label == LABEL_UNOBSERVED] = np.nan
    scan_distance_out = scan_distance.astype(np.float32)
    scan_distance_out[scan_label == LABEL_UNOBSERVED] = np.nan

    parameters: dict[str, Any] = {
        **{name: settings[name] for name in DEFAULT_PARAMETERS if name != "support_factor"},
        "support_factor": support_factor,
        "support_factor_calibrated": settings["support_factor"] is None,
        "min_region_points": int(min_region_points),
        "registration_rmse": float(registration_rmse),
        "reference_noise": reference_geometry.noise,
        "scan_noise": scan_geometry.noise,
        "alignment_residual": alignment_residual,
        "threshold": threshold,
        "reference_spacing_median": float(np.median(reference_geometry.spacing)),
        "scan_spacing_median": float(np.median(scan_geometry.spacing)),
        "nn_distance_over_spacing_quartile": nn_distance_quartile,
        "support_radius_median": max(support_factor * median_spacing, threshold),
        "cluster_radius_median": settings["cluster_factor"] * median_spacing,
        **reference_report,
        **scan_report,
        "n_reference_changed": int((reference_label == LABEL_CHANGED).sum()),
        "n_reference_unobserved": int((reference_label == LABEL_UNOBSERVED).sum()),
        "n_scan_changed": int((scan_label == LABEL_CHANGED).sum()),
        "n_scan_unobserved": int((scan_label == LABEL_UNOBSERVED).sum()),
        "n_dropped_clusters": int(sum(dropped.values())),
    }
    return Localisation(
        reference_label=reference_label,
        scan_label=scan_label,
        reference_distance=reference_distance_out,
        scan_distance=scan_distance_out,
        reference_region=reference_region,
        scan_region=scan_region,
        regions=regions,
        parameters=parameters,
    )
