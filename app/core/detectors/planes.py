"""PE-EMD: compare the planes extracted from two clouds (paper section III-C, eq. (5)).

The paper's randomised *fuzzy plane* extraction, steps 0-9:

1. ``L`` is an empty list of candidate planes with weights.
2. Draw 3 random non-collinear points ``P1, P2, P3``.
3. ``pi = (a, b, c, d)`` with ``a x + b y + c z = d`` through them, ``(a, b, c)`` unit.
4. Candidates ``rho`` in ``L`` close to ``pi``: ``|v_pi - v_rho| < epsilon`` and the distances of
   ``P1, P2, P3`` to ``rho`` all below ``delta``.
5-6. If none, add ``pi`` with weight 1; otherwise replace them all by their weighted average
   (``pi`` with weight 1), weight = sum of weights. (We renormalise the averaged ``(a, b, c)``
   to unit length.)
7. Repeat 2-6 ``N`` times.
8. If the largest weight in ``L`` is below ``m``, stop. Otherwise remove the points within
   ``eta`` of the heaviest plane(s) and record each plane with its number of such points.
9. Repeat 1-8 on the remaining points; stop when fewer than ``p`` remain.

Each cloud becomes planes ``(a, b, c, d)`` in R^4 weighted by inlier counts; eq. (1) with
Euclidean ground distance in R^4 gives ``d_PE``.

``paper``: exactly that, with fixed thresholds ``epsilon = 0.1``, ``delta = eta = 0.1``
(scene units, metres; the paper gives no values), ``N = 500``, ``m = 5``, ``p = 15``; the
normal's sign is whatever the cross product of the random triple gives. When a cloud yields
no plane (noise sigma >~ eta), eq. (1) is undefined and :class:`ExtractionError` is raised.

``improved``:

* **orientation**: ``(n, d)`` and ``(-n, -d)`` are the same plane but 2 apart in R^4. Every
  candidate is written in Hesse normal form relative to the reference's centroid ``o``
  (``n . (x - o) = d`` with ``d >= 0``), for both clouds, so step 6 averages like with like
  and equal planes get equal parameters.
* **thresholds from the data**: the noise ``sigma`` is estimated from local plane fits
  (median smallest eigenvalue of 12-neighbour covariances) and the spacing ``s`` from
  nearest-neighbour distances of the reference; ``eta = delta = max(2.5 sigma, 0.25 s)``,
  ``epsilon = clip(5 sigma / r, 0.05, 0.5)`` with ``r`` the RMS radius (the normal error of
  a triple with baseline ``~r``), ``p = max(15, 2% of the points)``.
* **voting and refinement**: steps 4-7 become one vectorised vote (each candidate's weight
  is the number of candidates it would absorb under the tests of step 4, so the result no
  longer depends on the order of the triples, and it is one matrix operation instead of a
  Python loop per triple); the 10 best-supported candidates (support >= ``m`` = 3) are
  refitted by least squares to their ``eta``-inliers (3 times) and the one with most
  inliers is extracted (RANSAC's criterion: the best-supported candidate alone is often a
  diagonal through two noisy walls). Its parameters then average all its points instead of
  ~N/9 random triples; planes with fewer than ``p`` inliers are not extracted, and a round
  without an acceptable plane is retried with fresh triples (3 failed rounds stop the
  extraction). ``N = 300``.
  At the end every point is counted for its *nearest* extracted plane (within ``eta``): the
  greedy removal of step 8 hands the points near an intersection to whichever plane
  happened to come first.
* **ground distance**: Euclidean in R^4 on ``(n, d / r)``, the offset in units of the
  reference's RMS radius ``r``, so distances (and ``unexplained_cost``) are scale-free.
* **weights**: inlier *fractions* of each cloud (a denser scan does not weigh more), plus the
  fraction of points explained by no plane as one more mass, at ground distance
  ``unexplained_cost`` from every plane; both sides then carry mass 1, so points that leave a
  plane for an object too small to become a plane still count.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from app.core.detectors.base import ChangeDetector, ParamSpec
from app.core.emd import earth_movers_distance
from app.core.errors import InputError


class ExtractionError(InputError):
    """The paper variant found no plane in one of the clouds, so eq. (1) is undefined."""


MAX_ROUNDS = 64
"""Safety cap on extraction rounds (steps 1-8), far above what real scenes need."""


@dataclass(frozen=True)
class PlaneSettings:
    """Thresholds of the extraction (the paper's step 0).

    Attributes
    ----------
    normal_tolerance : float
        ``epsilon``: candidates merge when their unit normals differ by less.
    merge_distance : float
        ``delta``: ... and the three sampled points lie within this of the candidate.
    inlier_distance : float
        ``eta``: points within this of an extracted plane belong to it.
    n_iterations : int
        ``N``: random triples per round.
    min_weight : int
        ``m``: stop when no candidate has gathered at least this many triples.
    min_points : int
        ``p``: stop when fewer points remain.
    orientation_origin : ndarray, shape (3,), or None
        Improved: write planes in Hesse form relative to this point (``d >= 0``).
    refine : bool
        Improved: least-squares refit of each extracted plane on its inliers, and keep only
        planes with at least ``min_points`` inliers.
    n_candidates : int
        Improved: how many of the heaviest candidates to refit; the one with most inliers wins.
    max_failed_rounds : int
        Improved: rounds without an acceptable plane before stopping (fresh triples each).
    """

    normal_tolerance: float
    merge_distance: float
    inlier_distance: float
    n_iterations: int
    min_weight: int
    min_points: int
    orientation_origin: NDArray[np.float64] | None = None
    refine: bool = False
    n_candidates: int = 1
    max_failed_rounds: int = 1


def _orient(planes: NDArray[np.float64], origin: NDArray[np.float64] | None) -> NDArray[np.float64]:
    """Rewrite planes ``(n, d)`` (``n . x = d``) relative to ``origin`` with ``d >= 0``."""
    if origin is None:
        return planes
    oriented = planes.copy()
    oriented[..., 3] = planes[..., 3] - planes[..., :3] @ origin
    flip = oriented[..., 3] < 0
    oriented[flip] *= -1.0
    return oriented


def _to_frame(
    plane: NDArray[np.float64], origin: NDArray[np.float64] | None
) -> NDArray[np.float64]:
    """Inverse of :func:`_orient` for one plane: back to ``n . x = d`` in the data frame."""
    if origin is None:
        return plane
    return np.array([*plane[:3], plane[3] + plane[:3] @ origin])


def _candidate_planes(
    points: NDArray[np.float64], count: int, rng: np.random.Generator
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Steps 2-3 for ``count`` triples at once: random non-collinear triples and their planes.

    Returns
    -------
    planes : ndarray, shape (count, 4)
        ``(a, b, c, d)`` with unit ``(a, b, c)``, sign from the cross product.
    triples : ndarray, shape (count, 3)
        Indices of ``P1, P2, P3``.
    """
    n_points = points.shape[0]
    planes: list[NDArray[np.float64]] = []
    triples: list[NDArray[np.int64]] = []
    found = 0
    for _ in range(100):
        drawn = rng.integers(0, n_points, size=(2 * (count - found) + 8, 3))
        first, second, third = (points[drawn[:, k]] for k in range(3))
        edge_1, edge_2 = second - first, third - first
        normals = np.cross(edge_1, edge_2)
        norms = np.linalg.norm(normals, axis=1)
        scale = np.linalg.norm(edge_1, axis=1) * np.linalg.norm(edge_2, axis=1)
        valid = norms > 1e-9 * np.maximum(scale, 1e-300)
        normals = normals[valid] / norms[valid, None]
        offsets = np.einsum("ij,ij->i", normals, first[valid])
        planes.append(np.column_stack([normals, offsets]))
        triples.append(drawn[valid])
        found += int(valid.sum())
        if found >= count:
            break
    all_planes = np.concatenate(planes)[:count]
    all_triples = np.concatenate(triples)[:count]
    return all_planes, all_triples


def _accumulate(
    candidates: NDArray[np.float64],
    triple_points: NDArray[np.float64],
    settings: PlaneSettings,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Steps 4-7: merge candidate planes into the weighted list ``L``.

    Parameters
    ----------
    candidates : ndarray, shape (N, 4)
        Planes in the representation being averaged (oriented when improved).
    triple_points : ndarray, shape (N, 3, 3)
        ``P1, P2, P3`` of each candidate, in the same frame as ``candidates``.

    Returns
    -------
    planes : ndarray, shape (k, 4)
    weights : ndarray, shape (k,)
    """
    capacity = candidates.shape[0]
    normals = np.empty((capacity, 3))
    offsets = np.empty(capacity)
    weights = np.empty(capacity)
    tolerance_squared = settings.normal_tolerance**2
    size = 0
    for plane, triple in zip(candidates, triple_points, strict=True):
        if size:
            normal_gap = normals[:size] - plane[:3]
            point_gap = np.abs(normals[:size] @ triple.T - offsets[:size, None])  # (size, 3)
            close = (np.einsum("ij,ij->i", normal_gap, normal_gap) < tolerance_squared) & (
                point_gap.max(axis=1) < settings.merge_distance
            )
            if close.any():
                merged_weight = 1.0 + weights[:size][close].sum()
                merged = plane * (1.0 / merged_weight)
                merged[:3] += weights[:size][close] @ normals[:size][close] / merged_weight
                merged[3] += weights[:size][close] @ offsets[:size][close] / merged_weight
                merged /= np.sqrt(merged[:3] @ merged[:3])
                keep = ~close
                kept = int(keep.sum())
                normals[:kept] = normals[:size][keep]
                offsets[:kept] = offsets[:size][keep]
                weights[:kept] = weights[:size][keep]
                normals[kept], offsets[kept], weights[kept] = merged[:3], merged[3], merged_weight
                size = kept + 1
                continue
        normals[size], offsets[size], weights[size] = plane[:3], plane[3], 1.0
        size += 1
    planes = np.column_stack([normals[:size], offsets[:size]])
    return planes, weights[:size]


class VoteWorkspace:
    """Reusable buffers for :func:`_vote`, one per extraction.

    A round's vote works on N x N arrays (N = 300 candidates: 0.7 MB each as float64).
    Allocated per round, every one is a fresh mapping (the service fixes glibc's mmap
    threshold at 128 KiB, :mod:`app.core.allocator`) whose page faults and zeroing cost more
    than the arithmetic: measured 1.1 ms instead of 0.4 ms per vote.
    """

    def __init__(self) -> None:
        self._floats = np.empty(0)
        self._flags = np.empty(0, dtype=bool)

    def arrays(
        self, size: int
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
        """Three float64 buffers and one bool buffer of ``size * size`` entries each, flat."""
        cells = size * size
        if self._floats.size < 3 * cells:
            self._floats = np.empty(3 * cells)
            self._flags = np.empty(cells, dtype=bool)
        first, second, third = (self._floats[k * cells : (k + 1) * cells] for k in range(3))
        return first, second, third, self._flags[:cells]


def _vote(
    candidates: NDArray[np.float64],
    triple_points: NDArray[np.float64],
    settings: PlaneSettings,
    workspace: VoteWorkspace | None = None,
    floor: int = 0,
) -> NDArray[np.float64]:
    """Improved steps 4-7: each candidate's weight is the number of candidates it would absorb.

    ``weight_i = #{j : |v_i - v_j| < epsilon and P_j1, P_j2, P_j3 within delta of plane i}``
    (``j = i`` included), computed for all pairs at once. The paper's sequential merging makes
    the result depend on the order of the triples and costs a Python loop per triple; the
    winner is refitted by least squares anyway, so only the vote matters.

    A candidate whose normal is close to fewer than ``floor`` candidates' normals cannot reach
    a weight of ``floor``; it gets that count (an upper bound of its weight, below
    ``floor``) and its point tests are skipped. The extraction only keeps weights >= ``m``,
    so with ``floor = m`` it picks the same candidates; the point tests of the others (about
    two thirds of them) are not worth computing.

    Parameters
    ----------
    candidates : ndarray, shape (N, 4)
    triple_points : ndarray, shape (N, 3, 3)
    settings : PlaneSettings
    workspace : VoteWorkspace, optional
        Buffers to reuse between rounds (default: fresh ones).
    floor : int
        Weights below this are only upper bounds (default 0: every weight exact).

    Returns
    -------
    ndarray, shape (N,)
    """
    count = candidates.shape[0]
    products, point_gap, heights, flags = (workspace or VoteWorkspace()).arrays(count)
    normals = candidates[:, :3]
    tolerance_squared = settings.normal_tolerance**2
    # |v_i - v_j|^2 = 2 - 2 v_i . v_j for unit normals, clipped at 0 (the clip cannot change
    # a comparison with a positive tolerance). In place: the same roundings as
    # `2.0 - 2.0 * (normals @ normals.T)`, without the temporaries.
    normal_gap_squared = products.reshape(count, count)
    np.matmul(normals, normals.T, out=normal_gap_squared)
    normal_gap_squared *= -2.0
    normal_gap_squared += 2.0
    if tolerance_squared <= 0.0:
        np.maximum(normal_gap_squared, 0.0, out=normal_gap_squared)
    normal_close = np.less(normal_gap_squared, tolerance_squared, out=flags.reshape(count, count))
    bounds = np.count_nonzero(normal_close, axis=1)
    rows = np.flatnonzero(bounds >= floor)
    weights = bounds.astype(np.float64)
    if rows.size == 0:
        return weights
    # distance of triple j's points to plane i, maximised over the three points, for the rows
    # i that can reach `floor`: (r, N). The products are computed for all rows (the same
    # matrix product, so the same roundings, whatever `floor` is) and then gathered.
    every_row = rows.size == count
    all_heights = products.reshape(count, count)  # the normal gaps are done with
    row_gap = point_gap[: rows.size * count].reshape(rows.size, count)
    row_heights = heights[: rows.size * count].reshape(rows.size, count)
    offsets = candidates[rows, 3:4]
    for corner in range(3):
        target = row_gap if corner == 0 else row_heights
        if every_row:
            np.matmul(normals, triple_points[:, corner, :].T, out=target)
        else:
            np.matmul(normals, triple_points[:, corner, :].T, out=all_heights)
            np.take(all_heights, rows, axis=0, out=target, mode="clip")  # valid rows: unbuffered
        target -= offsets
        np.abs(target, out=target)
        if corner:
            np.maximum(row_gap, row_heights, out=row_gap)
    support = normal_close[rows] if not every_row else normal_close
    support &= row_gap < settings.merge_distance
    weights[rows] = np.count_nonzero(support, axis=1)
    return weights


def _refit(points: NDArray[np.float64]) -> NDArray[np.float64]:
    """Least-squares plane ``(n, d)`` through ``points`` (n, 3), n >= 3."""
    centroid = points.mean(axis=0)
    _, _, right = np.linalg.svd(points - centroid, full_matrices=False)
    normal = right[-1]
    return np.array([*normal, normal @ centroid])


Refinement = tuple[NDArray[np.float64], NDArray[np.bool_]]
"""A refitted plane ``(n, d)`` (data frame), shape (4,), and its inlier mask, shape (n,)."""


def _refined(
    points: NDArray[np.float64],
    plane: NDArray[np.float64],
    settings: PlaneSettings,
    known: dict[tuple[int, bytes], Refinement] | None = None,
) -> Refinement:
    """Least-squares refit of ``plane`` (data frame) on its ``eta``-inliers, three times.

    Each refit depends on the inlier mask only, so once a candidate's mask equals one another
    candidate had at the same step, the rest of its refinement is that candidate's: ``known``
    (one dict per set of ``points``) remembers them. The 10 best-supported candidates of a
    round are mostly the same surface, and their masks meet after one or two refits. And a
    refit whose mask comes out unchanged is a fixed point (the next refit is the same
    computation), so the loop stops there. Both skip refits without changing the result.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    plane : ndarray, shape (4,)
    settings : PlaneSettings
    known : dict, optional
        ``(step, inlier mask bytes) -> result``, filled in by this call.

    Returns
    -------
    plane : ndarray, shape (4,)
    inliers : ndarray, shape (n,), bool
    """
    inliers = np.abs(points @ plane[:3] - plane[3]) < settings.inlier_distance
    visited: list[tuple[int, bytes]] = []
    for step in range(3):
        if np.count_nonzero(inliers) < 3:
            break
        if known is not None:
            key = (step, np.packbits(inliers).tobytes())
            if key in known:
                plane, inliers = known[key]
                break
            visited.append(key)
        plane = _refit(points[inliers])
        previous = inliers
        inliers = np.abs(points @ plane[:3] - plane[3]) < settings.inlier_distance
        if np.array_equal(inliers, previous):
            break  # a fixed point: every further refit gives this plane and mask again
    if known is not None:
        known.update(dict.fromkeys(visited, (plane, inliers)))
    return plane, inliers


def extract_fuzzy_planes(
    points: NDArray[np.float64], settings: PlaneSettings, rng: np.random.Generator
) -> tuple[NDArray[np.float64], NDArray[np.float64], int]:
    """The paper's steps 0-9.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    settings : PlaneSettings
    rng : numpy.random.Generator

    Returns
    -------
    planes : ndarray, shape (k, 4)
        ``(a, b, c, d)``; relative to ``settings.orientation_origin`` with ``d >= 0`` when that
        is set, otherwise ``a x + b y + c z = d`` in the data frame.
    counts : ndarray, shape (k,)
        Number of points in each plane's ``eta``-neighbourhood (removed with it).
    n_unexplained : int
        Points left when the extraction stopped.
    """
    origin = settings.orientation_origin
    remaining = points
    found_planes: list[NDArray[np.float64]] = []
    counts: list[int] = []
    failed_rounds = 0
    workspace = VoteWorkspace()
    for _ in range(MAX_ROUNDS):
        if remaining.shape[0] < max(settings.min_points, 3):
            break
        candidates, triples = _candidate_planes(remaining, settings.n_iterations, rng)
        if candidates.shape[0] == 0:
            break
        triple_points = remaining[triples]
        if origin is not None:
            candidates = _orient(candidates, origin)
            triple_points = triple_points - origin
        if settings.refine:
            # Improved: vote, then of the `n_candidates` best-supported candidates (with
            # support >= m) keep the one whose least-squares refit has the most inliers.
            weights = _vote(candidates, triple_points, settings, workspace, settings.min_weight)
            order = np.argsort(-weights, kind="stable")[: settings.n_candidates]
            order = order[weights[order] >= settings.min_weight]
            known: dict[tuple[int, bytes], Refinement] = {}
            best = max(
                (
                    _refined(remaining, _to_frame(candidates[k], origin), settings, known)
                    for k in order
                ),
                key=lambda refined: int(refined[1].sum()),
                default=None,
            )
            if best is None or int(best[1].sum()) < settings.min_points:
                # A weak round (few random triples happened to share a plane) is not proof
                # that no plane is left: retry with fresh triples before stopping.
                failed_rounds += 1
                if failed_rounds >= settings.max_failed_rounds:
                    break
                continue
            frame_plane, inliers = best
            found_planes.append(_orient(frame_plane, origin))
            counts.append(int(inliers.sum()))
            remaining = remaining[~inliers]
            continue
        planes, weights = _accumulate(candidates, triple_points, settings)
        if weights.max() < settings.min_weight:
            break
        heaviest = weights.max()
        removed_any = False
        for plane in planes[weights == heaviest]:
            inliers = np.abs(remaining @ plane[:3] - plane[3]) < settings.inlier_distance
            n_inliers = int(inliers.sum())
            if n_inliers == 0:
                continue
            found_planes.append(plane)
            counts.append(n_inliers)
            remaining = remaining[~inliers]
            removed_any = True
        if not removed_any:
            break
    if not found_planes:
        return np.empty((0, 4)), np.empty(0), int(remaining.shape[0])
    planes = np.array(found_planes)
    if settings.refine:
        # Improved: the greedy removal gives the points near an intersection to whichever
        # plane came first (a random order); count each point for its nearest plane instead.
        frame_planes = np.array([_to_frame(plane, origin) for plane in planes])
        heights = np.abs(points @ frame_planes[:, :3].T - frame_planes[:, 3])  # (n, k)
        nearest = heights.argmin(axis=1)
        explained = heights[np.arange(points.shape[0]), nearest] < settings.inlier_distance
        final_counts = np.bincount(nearest[explained], minlength=planes.shape[0])
        return planes, final_counts.astype(np.float64), int(points.shape[0] - explained.sum())
    return planes, np.array(counts, dtype=np.float64), int(remaining.shape[0])


def estimate_noise_and_spacing(
    points: NDArray[np.float64], rng: np.random.Generator, n_neighbours: int = 12
) -> tuple[float, float]:
    """Surface noise and point spacing from local plane fits.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    rng : numpy.random.Generator
        Picks up to 500 query points.
    n_neighbours : int

    Returns
    -------
    noise_std : float
        ``sqrt(median smallest eigenvalue of the neighbourhood covariance * (k-1)/(k-3))``:
        the residual standard deviation of a local plane fit (corrected for the 3 fitted
        degrees of freedom); the median ignores edges and corners.
    spacing : float
        Median distance to the nearest neighbour.
    """
    n_points = points.shape[0]
    neighbours = min(n_neighbours, n_points)
    queries = points[rng.choice(n_points, min(500, n_points), replace=False)]
    tree = cKDTree(points)
    distances, indices = tree.query(queries, k=neighbours)
    spacing = float(np.median(distances[:, 1])) if neighbours > 1 else 0.0
    patches = points[indices]  # (q, k, 3)
    centred = patches - patches.mean(axis=1, keepdims=True)
    covariances = np.einsum("qki,qkj->qij", centred, centred) / max(neighbours - 1, 1)
    smallest = np.linalg.eigvalsh(covariances)[:, 0]
    correction = (neighbours - 1) / max(neighbours - 3, 1)
    noise_std = float(np.sqrt(max(np.median(smallest), 0.0) * correction))
    return noise_std, spacing


class PlanesDetector(ChangeDetector):
    """PE-EMD change detector; see the module docstring for the two variants.

    Parameters
    ----------
    variant : {"improved", "paper"}
    random_state : int
    n_iterations : int
        ``N``, random triples per round (paper 500: with 200, the paper's merge stopped before
        the first plane on half of the corridor pairs at variance 1e-3; improved 300).
    min_weight : int
        ``m``: paper 5 (triples merged into the heaviest candidate); improved 3 (votes).
    normal_tolerance, merge_distance, inlier_distance : float
        Paper only: ``epsilon`` (0.1), ``delta`` and ``eta`` (0.1, scene units).
    min_points : int
        Paper only: ``p`` (15). Improved: ``max(15, min_point_fraction * n)``.
    min_point_fraction : float
        Improved only (0.02).
    noise_multiplier : float
        Improved only: ``eta = delta = max(noise_multiplier * sigma, 0.25 * spacing)`` (2.5).
    unexplained_cost : float
        Improved only: ground distance between the "no plane" mass and any plane (1.0).
    **params
        The common ones; see :mod:`app.core.detectors.base`.
    """

    method: ClassVar[str] = "planes"
    _specs: ClassVar[dict[str, ParamSpec]] = {
        "n_iterations": ParamSpec("int", 3, 100_000),
        "min_weight": ParamSpec("int", 1, 100_000),
        "normal_tolerance": ParamSpec("float", 0.0, 2.0),
        "merge_distance": ParamSpec("float", 0.0, None),
        "inlier_distance": ParamSpec("float", 0.0, None),
        "min_points": ParamSpec("int", 3, 10_000_000),
        "min_point_fraction": ParamSpec("float", 0.0, 1.0),
        "noise_multiplier": ParamSpec("float", 0.0, 100.0),
        "unexplained_cost": ParamSpec("float", 0.0, 100.0),
    }
    _variant_defaults: ClassVar[dict[str, dict[str, Any]]] = {
        "improved": {
            "n_iterations": 300,
            "min_weight": 3,
            "min_point_fraction": 0.02,
            "noise_multiplier": 2.5,
            "unexplained_cost": 1.0,
        },
        # The paper's sequential merge is a Python loop per triple: fewer, smaller extractions
        # keep detect() within ~1-2 s of CPU at 200k points.
        "paper": {
            "max_points": 2000,
            "n_resamples": 10,
            "n_iterations": 500,
            "min_weight": 5,
            "normal_tolerance": 0.1,
            "merge_distance": 0.1,
            "inlier_distance": 0.1,
            "min_points": 15,
        },
    }

    def _context(
        self,
        reference: NDArray[np.float64],
        scan: NDArray[np.float64],
        rng: np.random.Generator,
    ) -> dict[str, Any]:
        params = self.params
        if self.variant == "paper":
            settings = PlaneSettings(
                normal_tolerance=params["normal_tolerance"],
                merge_distance=params["merge_distance"],
                inlier_distance=params["inlier_distance"],
                n_iterations=params["n_iterations"],
                min_weight=params["min_weight"],
                min_points=params["min_points"],
            )
            return {"settings": settings}
        origin = reference.mean(axis=0)
        rms_radius = float(np.sqrt(np.mean(np.sum((reference - origin) ** 2, axis=1))))
        noise_std, spacing = estimate_noise_and_spacing(reference, rng)
        inlier_distance = max(params["noise_multiplier"] * noise_std, 0.25 * spacing, 1e-9)
        normal_tolerance = float(np.clip(5.0 * noise_std / max(rms_radius, 1e-12), 0.05, 0.5))
        min_points = max(15, int(params["min_point_fraction"] * reference.shape[0]))
        settings = PlaneSettings(
            normal_tolerance=normal_tolerance,
            merge_distance=inlier_distance,
            inlier_distance=inlier_distance,
            n_iterations=params["n_iterations"],
            min_weight=params["min_weight"],
            min_points=min_points,
            orientation_origin=origin,
            refine=True,
            n_candidates=10,
            max_failed_rounds=3,
        )
        return {
            "settings": settings,
            "noise_std": noise_std,
            "spacing": spacing,
            "rms_radius": max(rms_radius, 1e-12),
        }

    def descriptor(
        self, points: NDArray[np.float64], context: dict[str, Any]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Weighted points for eq. (1): planes (k, 4) and their weights (k,).

        The random triples are drawn from a generator seeded by ``random_state`` and the
        points' bytes: the same cloud always gives the same planes (so ``d(S, S) = 0``), two
        different clouds get independent draws.

        Improved: inlier fractions plus, as the last row, the unexplained fraction (its plane
        row is NaN and is handled by :meth:`_score`).
        """
        content = hashlib.blake2b(np.ascontiguousarray(points).tobytes(), digest_size=8)
        rng = np.random.default_rng([self.random_state, int.from_bytes(content.digest(), "little")])
        planes, counts, n_unexplained = extract_fuzzy_planes(points, context["settings"], rng)
        if self.variant == "paper":
            return planes, counts
        fractions = np.append(counts, n_unexplained) / points.shape[0]
        return np.vstack([planes, np.full((1, 4), np.nan)]), fractions

    def _score(
        self,
        first: NDArray[np.float64],
        second: NDArray[np.float64],
        context: dict[str, Any],
        rng: np.random.Generator,
        is_resample: bool,
    ) -> float:
        planes_a, weights_a = self.descriptor(first, context)
        planes_b, weights_b = self.descriptor(second, context)
        if self.variant == "paper":
            if planes_a.shape[0] == 0 or planes_b.shape[0] == 0:
                # Eq. (1) is undefined without mass on both sides.
                if is_resample:
                    return float("nan")  # calibration drops it
                raise ExtractionError(
                    f"the paper's plane extraction found {planes_a.shape[0]} plane(s) in the "
                    f"reference and {planes_b.shape[0]} in the scan with its fixed thresholds "
                    f"(eta = {self.params['inlier_distance']:g}); eq. (1) needs planes on both "
                    "sides. Noisier data needs larger thresholds, or use variant='improved'"
                )
            ground = np.linalg.norm(planes_a[:, None, :] - planes_b[None, :, :], axis=2)
            return earth_movers_distance(weights_a, weights_b, ground).distance
        # (n, d / r): offsets in units of the reference's RMS radius, so the ground distance
        # (and unexplained_cost) mean the same in a corridor and in a warehouse.
        scale = np.array([1.0, 1.0, 1.0, 1.0 / context["rms_radius"]])
        ground = np.linalg.norm(
            planes_a[:-1, None, :] * scale - planes_b[None, :-1, :] * scale, axis=2
        )
        cost = self.params["unexplained_cost"]
        full = np.zeros((planes_a.shape[0], planes_b.shape[0]))
        full[:-1, :-1] = ground
        full[-1, :-1] = cost
        full[:-1, -1] = cost
        return earth_movers_distance(weights_a, weights_b, full).distance
