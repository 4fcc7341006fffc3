"""Distance of each point to the other cloud's surface (C2M/M3C2-like), and what it calibrates.

Each neighbour ``q`` (in the other cloud, around the point's nearest point there) stands for a
disc of radius ``r(q) = max(f * s(q), tau)`` on its fitted plane.  The distance of ``p`` is the
smallest point-to-plane distance to the discs ``p`` projects into, or its nearest-point
distance when it projects into none (the other cloud has no surface there).  A matched point
(its nearest point lies within that point's support radius and ``p`` within the change
threshold of that point's plane: never a candidate) gets that one plane's offset.  The
support factor ``f`` is calibrated on the data (:func:`support_factor`), and the misalignment
left after registration is measured on matched points (:func:`alignment_residual`).  The
candidates judged by their surface rather than one point's distance are
:mod:`~app.core.localise.surface_levels`'.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.core.cloud import MIN_POINTS
from app.core.localise.neighbourhoods import kernel_nearest
from app.core.localise.settings import CHUNK, GATHER_CHUNK, QUERY_CHUNK
from app.core.localise.surface import LocalGeometry
from app.core.spatial_order import ordered_chunks
from app.core.threads import concurrently, for_each_chunk

__all__ = [
    "Side",
    "alignment_residual",
    "nearest_in",
    "pair_median_spacing",
    "pair_nn_distance_quartile",
    "support_factor",
    "surface_distance",
]

SUPPORT_FACTOR_QUANTILE = 0.25
SUPPORT_FACTOR_PER_QUANTILE = 3.5
"""Calibrated support factor = 3.5 x the lower quartile of nearest-neighbour distances in local
spacings (~1.3 for independent lidar samplings; the quartile ignores up to 75 % of points
being changed or unobserved)."""
SUPPORT_FACTOR_RANGE = (0.5, 2.0)
ALIGNMENT_SAMPLE = 20_000
"""Points of each cloud whose plane offsets measure the alignment residual."""
DISTANCE_BLOCK = 4 * CHUNK
"""Points per task of :func:`surface_distance` on its threads (~5 ms of CPU a task at 1M
points: 31 of them, so that the last one's wait is short)."""


@dataclass(frozen=True)
class Side:
    """One cloud of a comparison, its local surfaces and its nearest points in the other cloud.

    Attributes
    ----------
    name : {"reference", "scan"}
        Prefix of the report's keys.
    region_kind : {"removed", "added"}
        Kind of the regions its changed points form.
    points : ndarray, shape (n, 3), float64
    origins : ndarray, shape (k, 3), or None
        This cloud's sensor positions (reference frame), one per station, if known.
    station : ndarray, shape (n,), int64, or None
        Index into ``origins`` of the station that took each point, if known or recovered
        (None with one station: every point is its).
    stations_unknown : bool
        A lidar cloud merged from several stations that are neither known nor recovered
        (``origins`` None): ``origin_free_test="auto"`` uses the surface test against it.
    trajectory_rays : (ndarray, ndarray) or None
        Taken along a trajectory: ``origins`` are its pseudo-stations' sensor positions,
        ``station`` each point's pseudo-station, and these ``(returns, bounds)`` the points
        each pseudo-station's rays end on (:class:`app.core.trajectory_poses.SensorGroups`);
        the other cloud's candidates get the trajectory test
        (:mod:`app.core.localise.trajectory_visibility`).
    geometry : LocalGeometry
        Of ``points``.
    nearest_distance : ndarray, shape (n,), float64
        Distance of each point to its nearest point in the other cloud.
    nearest_index : ndarray, shape (n,), uint32
        Index of that point in the other cloud.
    """

    name: str
    region_kind: str
    points: NDArray[np.float64]
    origins: NDArray[np.float64] | None
    geometry: LocalGeometry
    nearest_distance: NDArray[np.float64]
    nearest_index: NDArray[np.uint32]
    station: NDArray[np.int64] | None = None
    stations_unknown: bool = False
    trajectory_rays: tuple[NDArray[np.int64], NDArray[np.int64]] | None = None


def nearest_in(
    points: NDArray[np.float64],
    other: LocalGeometry,
    order: NDArray[np.intp] | None = None,
    own_tree: Any = None,
    threads: int = 1,
) -> tuple[NDArray[np.float64], NDArray[np.uint32]]:
    """Distance to and index of each point's nearest point in ``other``.

    By the compiled kernel's trees when both clouds have theirs (:func:`kernel_nearest`,
    ~30 % less CPU at 1M points), else by ``other``'s KD-tree: the same numbers.

    Parameters
    ----------
    points : ndarray, shape (p, 3)
    other : LocalGeometry
    order : ndarray, shape (p,), intp, optional
        ``points``' :func:`~app.core.spatial_order.spatial_order`: queried a chunk of nearby
        points at a time (faster on a shuffled cloud; the same answers).
    own_tree : object, optional
        The compiled kernel's tree of ``points`` (:attr:`LocalGeometry.kernel_tree`).
    threads : int
        Threads of the kernel's search (:func:`kernel_nearest`; the same answers).

    Returns
    -------
    distance : ndarray, shape (p,), float64
    index : ndarray, shape (p,), uint32
    """
    if own_tree is not None and other.kernel_tree is not None:
        found = kernel_nearest(points, own_tree, other.kernel_tree, other.tree, threads)
        if found is not None:
            return found
    if order is None:
        return other.tree.query(points, k=1)
    distance = np.empty(len(points))
    index = np.empty(len(points), dtype=np.uint32)
    for rows in ordered_chunks(order, len(points), QUERY_CHUNK):
        distance[rows], index[rows] = other.tree.query(points[rows], k=1)
    return distance, index


def pair_median_spacing(reference_side: Side, scan_side: Side) -> float:
    """The median spacing of both clouds' points."""
    # both clouds' values in one array, partitioned in place (no copy: 80 MB at 5M + 5M)
    both_spacings = np.concatenate([reference_side.geometry.spacing, scan_side.geometry.spacing])
    return float(np.median(both_spacings, overwrite_input=True))


def pair_nn_distance_quartile(reference_side: Side, scan_side: Side, threads: int = 1) -> float:
    """The :data:`SUPPORT_FACTOR_QUANTILE` quantile of each point's nearest-neighbour distance
    in the other cloud, in that cloud's local spacings (both clouds' points); from 2
    ``threads`` each cloud's values (a gather of the other's spacings) on a thread of its own."""
    n_reference = len(reference_side.points)
    relative_nn_distance = np.empty(n_reference + len(scan_side.points))

    def relative(own: Side, other: Side, out: NDArray[np.float64]) -> None:
        np.divide(own.nearest_distance, other.geometry.spacing[own.nearest_index], out=out)

    concurrently(
        threads,
        lambda: relative(reference_side, scan_side, relative_nn_distance[:n_reference]),
        lambda: relative(scan_side, reference_side, relative_nn_distance[n_reference:]),
    )
    # one quantile (a partition of both clouds' values, in place) for the report and the
    # calibrated support factor
    return float(np.quantile(relative_nn_distance, SUPPORT_FACTOR_QUANTILE, overwrite_input=True))


def support_factor(nn_distance_quartile: float, requested: float | None) -> float:
    """The support factor ``f``: ``requested``, or calibrated from the clouds when None.

    Parameters
    ----------
    nn_distance_quartile : float
        The :data:`SUPPORT_FACTOR_QUANTILE` quantile of each point's nearest-neighbour distance
        in the other cloud, in that cloud's local spacings (both clouds' points).
    requested : float or None

    Returns
    -------
    float
        :data:`SUPPORT_FACTOR_PER_QUANTILE` x ``nn_distance_quartile``, clipped to
        :data:`SUPPORT_FACTOR_RANGE`.
    """
    if requested is not None:
        return float(requested)
    low, high = SUPPORT_FACTOR_RANGE
    return float(np.clip(SUPPORT_FACTOR_PER_QUANTILE * nn_distance_quartile, low, high))


def surface_distance(
    points: NDArray[np.float64],
    nn_distance: NDArray[np.float64],
    nn_index: NDArray[np.integer],
    *,
    other: LocalGeometry,
    threshold: float,
    support_factor: float,
    change_threshold: float | None = None,
    with_plane_offset: bool = False,
    threads: int = 1,
) -> tuple[NDArray[np.float64], NDArray[np.bool_], NDArray[np.float64] | None]:
    """Distance of each point to the other cloud's supported local surface.

    A point whose nearest point in the other cloud lies within that point's support radius
    (``max(support_factor * spacing, tau)``), and within ``change_threshold`` of that point's
    plane or of the point itself, is *matched*: the other cloud has surface right there, so it
    is never a candidate, and its distance is the offset from the plane of its nearest point's
    neighbourhood (one plane: most points are matched, and this keeps their cost at one
    gather).  Any other point is compared with every neighbour ``q`` of its nearest point (a
    disc of radius ``max(support_factor * s(q), tau)`` on ``q``'s plane) and is a candidate
    when farther than ``change_threshold`` from all of them and from its nearest point.

    The support radius is a tolerance *across* the other cloud's surface (its sampling): on a
    floor seen at grazing angles it reaches tens of centimetres, and a point that far *above*
    the floor is not on it.  Along the normal the tolerance is the change threshold.  A point
    of the other cloud is itself on that cloud's surface, so a point within the change
    threshold of one is not a change, whatever the plane fitted there (across an edge or a
    corner, or on a sparse cloud, it can be tilted far off both).

    Parameters
    ----------
    points : ndarray, shape (p, 3)
    nn_distance, nn_index : ndarray, shape (p,)
        Nearest point of the other cloud.
    other : LocalGeometry
        The other cloud (its neighbour index not yet released).
    threshold : float
        ``tau``: the noise threshold, the smallest support radius.
    support_factor : float
    change_threshold : float, optional
        ``max(tau, min_change_distance)``: the largest distance from the other cloud's surface
        that is not a change (at least ``threshold``).  None: ``threshold``, and every point
        within the support radius of its nearest point is matched whatever its plane offset
        (the alignment residual's sample).
    with_plane_offset : bool
        Also return the signed offsets (for the alignment residual; 8 bytes a point).
    threads : int
        Threads that fill the blocks of :data:`DISTANCE_BLOCK` points (each its own rows: the
        same result on any number; the other cloud's distances, on a thread of their own, may
        finish first, and this cloud's blocks then still share both cores).

    Returns
    -------
    distance : ndarray, shape (p,)
        Matched points: absolute offset from the nearest point's plane.  Unmatched points:
        the smallest point-to-plane distance over the neighbours of the nearest point whose
        support disc ``p`` projects into; the nearest-point distance when there is none.
    candidate : ndarray, shape (p,), bool
        Unmatched, ``distance > change_threshold`` and farther than that from the nearest
        point (``distance > tau`` without ``change_threshold``).
    nearest_plane_offset : ndarray, shape (p,), or None
        With ``with_plane_offset``: the signed offset from the nearest point's plane for
        matched points, NaN elsewhere.
    """
    if change_threshold is not None and change_threshold < threshold:
        raise ValueError(f"change_threshold {change_threshold} is below tau {threshold}")
    count = points.shape[0]
    job = _DistanceJob(
        points=points,
        nn_distance=nn_distance,
        nn_index=nn_index,
        other=other,
        threshold=threshold,
        support_factor=support_factor,
        change_threshold=change_threshold,
        distance=np.empty(count),
        candidate=np.zeros(count, dtype=bool),
        nearest_plane_offset=np.full(count, np.nan) if with_plane_offset else None,
    )
    for_each_chunk(job.block, range(0, count, DISTANCE_BLOCK), threads)
    return job.distance, job.candidate, job.nearest_plane_offset


@dataclass(frozen=True)
class _DistanceJob:
    """:func:`surface_distance`'s inputs and outputs; :meth:`block` fills one block's rows
    (its own: the blocks may run on any number of threads to the same result).

    Attributes
    ----------
    points : ndarray, shape (p, 3)
    nn_distance, nn_index : ndarray, shape (p,)
    other : LocalGeometry
    threshold, support_factor : float
    change_threshold : float or None
    distance : ndarray, shape (p,), float64
    candidate : ndarray, shape (p,), bool
    nearest_plane_offset : ndarray, shape (p,), float64, or None
    """

    points: NDArray[np.float64]
    nn_distance: NDArray[np.float64]
    nn_index: NDArray[np.integer]
    other: LocalGeometry
    threshold: float
    support_factor: float
    change_threshold: float | None
    distance: NDArray[np.float64]
    candidate: NDArray[np.bool_]
    nearest_plane_offset: NDArray[np.float64] | None

    def block(self, start: int) -> None:
        """The :data:`DISTANCE_BLOCK` rows from ``start``: the matched ones by their nearest
        point's plane (:data:`CHUNK` at a time), then the others by the discs of its
        neighbours (:data:`GATHER_CHUNK` at a time)."""
        stop = min(start + DISTANCE_BLOCK, self.points.shape[0])
        unmatched = np.concatenate(
            [self._matched(step, min(step + CHUNK, stop)) for step in range(start, stop, CHUNK)]
        )
        for step in range(0, unmatched.shape[0], GATHER_CHUNK):
            self._on_discs(unmatched[step : step + GATHER_CHUNK])

    def _matched(self, start: int, stop: int) -> NDArray[np.int64]:
        """Fill the matched rows of ``start:stop``; return the others (shape (u,))."""
        chunk = slice(start, stop)
        other, nn_distance = self.other, self.nn_distance[chunk]
        nearest = self.nn_index[chunk]
        nearest_support = np.maximum(self.support_factor * other.spacing[nearest], self.threshold)
        offset = (
            np.einsum("pd,pd->p", self.points[chunk], other.normal[nearest])
            - other.plane_constant[nearest]
        )
        matched = nn_distance <= nearest_support
        if self.change_threshold is not None:
            # on the nearest point's plane, or as close to that point (a sample of the surface)
            # as a change may be: a plane fitted across an edge or a corner can be far off both
            near_surface = np.abs(offset) <= self.change_threshold
            matched &= near_surface | (nn_distance <= self.change_threshold)
        rows = start + np.flatnonzero(matched)
        if self.nearest_plane_offset is not None:
            self.nearest_plane_offset[rows] = offset[matched]
        self.distance[rows] = np.abs(offset[matched])
        return start + np.flatnonzero(~matched)

    def _on_discs(self, rows: NDArray[np.int64]) -> None:
        """Fill ``rows`` (unmatched, shape (c,)) by the support discs of their nearest point's
        neighbours."""
        other, threshold, change_threshold = self.other, self.threshold, self.change_threshold
        query = self.points[rows]
        nn_distance = self.nn_distance[rows]
        neighbours = other.neighbor_index[self.nn_index[rows]]  # (c, K) around the nearest point
        normals = other.normal[neighbours]
        support_radius = np.maximum(self.support_factor * other.spacing[neighbours], threshold)
        offset = query[:, None, :] - other.points[neighbours]
        along_normal = np.einsum("ckd,ckd->ck", offset, normals)
        lateral_squared = np.einsum("ckd,ckd->ck", offset, offset) - along_normal**2
        supported = lateral_squared <= support_radius**2
        plane_offset = np.einsum("cd,ckd->ck", query, normals) - other.plane_constant[neighbours]
        plane_distance = np.where(supported, np.abs(plane_offset), np.inf).min(axis=1)
        distance = np.where(np.isfinite(plane_distance), plane_distance, nn_distance)
        self.distance[rows] = distance
        if change_threshold is None:
            self.candidate[rows] = distance > threshold
        else:
            self.candidate[rows] = (distance > change_threshold) & (nn_distance > change_threshold)


def alignment_residual(
    reference: Side, scan: Side, *, threshold: float, support_factor: float
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
    reference, scan : Side
        The two clouds, their neighbour indices not yet released.
    threshold : float
        Preliminary ``tau`` (noise and registration_rmse only).
    support_factor : float

    Returns
    -------
    float
        ``sqrt(mean over both directions of max(0, spread^2 - noise^2))``.
    """
    excess_variances = []
    for own, other in ((reference, scan), (scan, reference)):
        step = max(1, own.points.shape[0] // ALIGNMENT_SAMPLE)
        sample = slice(None, None, step)
        _, _, offset = surface_distance(
            own.points[sample],
            own.nearest_distance[sample],
            own.nearest_index[sample],
            other=other.geometry,
            threshold=threshold,
            support_factor=support_factor,
            with_plane_offset=True,
        )
        assert offset is not None  # with_plane_offset=True
        offset = offset[np.isfinite(offset)]
        if offset.size < MIN_POINTS:
            continue
        spread = 1.4826 * float(np.median(np.abs(offset - np.median(offset))))
        other_k = other.geometry.neighbor_index.shape[1]
        noise_variance = own.geometry.noise**2 + other.geometry.noise**2 / other_k
        excess_variances.append(max(0.0, spread**2 - noise_variance))
    return math.sqrt(float(np.mean(excess_variances))) if excess_variances else 0.0
