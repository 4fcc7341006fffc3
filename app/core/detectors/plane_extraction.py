"""The paper's randomised fuzzy plane extraction (section III-C, steps 0-9) and its improved
vote and least-squares refinement.

The steps, and what each variant changes, are described in :mod:`app.core.detectors.planes`,
whose detector calls :func:`extract_fuzzy_planes` with the :class:`PlaneSettings` of its
variant.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

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
    threshold at 128 KiB, :mod:`app.kit.allocator`) whose page faults and zeroing cost more
    than the arithmetic (figures in docs/performance.md).
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
