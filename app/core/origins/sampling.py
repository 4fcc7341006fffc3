"""Whether a cloud was sampled by lidars: rings of returns at regular angular steps.

Used by :func:`~app.core.origins.station_recovery.resolve_stations` to decide, for a cloud that no
single origin explains, whether to search its stations (a survey merged from several lidar
stations) or not (uniform, random or gridded points, which have none and must not pay the
search, nor get the origin-free surface test meant for merged lidar clouds).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.origins.voxels import whole_voxels

__all__ = ["LidarSampling", "lidar_sampling"]

SAMPLING_MAX_POINTS = 100_000
"""Points whose sampling is measured (beyond this, whole voxels of them:
:func:`~app.core.origins.voxels.whole_voxels`)."""
SAMPLING_QUERIES = 5_000
"""Points whose nearest neighbours are examined."""
SAMPLING_NEIGHBOURS = 6
"""Neighbours searched for twins: six, so that a ring's neighbours are found among the returns of
other stations interleaved with them in a dense merged survey."""
TWIN_TOLERANCE = 0.02
"""Two neighbours are twins when their distances differ by at most this share."""
OPPOSITE_COSINE = -0.98
"""... and lie on opposite sides of the point (within 11 degrees of a straight line)."""
MIN_TWIN_SHARE = 0.035
"""A lidar's sampling: at least this share of points with opposite twin neighbours (the returns
before and after them on their ring), where the points' noise is small against their spacing
(:data:`QUIET_NOISE_RATIO`).  Measured with six neighbours (3 subsamples each): merged
1M-point surveys of 5 stations 0.051-0.15 (four neighbours: 0.027-0.088, too near uniform
points); uniform points on planes and volumes 0.021 (exact planes, 300k points on a box's faces:
0.032-0.033), their 5-10 cm voxel centroids 0.018-0.019, random points 0.007, the paper's uniform
corridor 0.009."""
MIN_NOISY_TWIN_SHARE = 0.015
"""... and this share where the noise is as large as the spacing (:data:`NOISY_NOISE_RATIO`).

Range noise moves a return along its ray by a fixed length (1 cm in the synthetic surveys), while
the spacing of the returns shrinks with the density: the twins' equal distances and straight
angle are lost in the noise as the cloud gets denser, and the share falls with the noise ratio,
not with the scan pattern.  The same five-station warehouse survey (seed 18), its reference,
noise ratio / twin share: 250k points 0.17 / 0.30, 1M 0.31 / 0.15, 4M 0.48 / 0.08, 20M about
0.67 / 0.033 (a 250k-point survey with the 20M survey's noise-to-spacing ratio, 9 cm noise:
0.67 / 0.04); rooms and corridors at that ratio 0.023-0.069.  Points without a lattice lose
their chance twins the same way: uniform points on a box's faces with 0-10 cm noise, ratio 0 /
0.23 / 0.40 / 0.51 / 0.65 / 0.78: twin share 0.033 / 0.018 / 0.011 / 0.008 / 0.008 / 0.008; a
noisy 5 cm grid 0.47 / 0.011; random points and the paper's corridor (30k-1M points) 0.80-0.91 /
0.004-0.008."""
QUIET_NOISE_RATIO = 0.35
"""Noise ratio (:attr:`LidarSampling.noise_ratio`) up to which :data:`MIN_TWIN_SHARE` applies;
the share needed falls linearly from there to :data:`MIN_NOISY_TWIN_SHARE` at
:data:`NOISY_NOISE_RATIO`.  KITTI frames 0.22-0.25, Budapest frames 0.42-0.53 (twin share
0.10-0.16), the real MLS bike parking 0.23-0.39 (0.020-0.036), the thinned TLS classroom 0.01."""
NOISY_NOISE_RATIO = 0.6
"""Noise ratio from which :data:`MIN_NOISY_TWIN_SHARE` applies."""
PLANE_NEIGHBOURS = 16
"""Neighbours whose best plane measures a point's noise (the RMS of their distances to it)."""
MIN_SPACING_SPREAD = 1.5
"""... and spacing that varies across the cloud (90th over 10th percentile of the nearest
neighbour distance): a regular grid has twins too, but one spacing (5 cm grid with 3 mm noise:
1.16).  Lidars: 1.9-17 (single-station corridors 1.9-2.5 at 100k-1M points, merged 1M
corridors 2.3-2.7: long walls seen at similar ranges; rooms, warehouses and Velodyne frames
3-17); random points 2.8-4.1 (they fail the twin share)."""


@dataclass(frozen=True)
class LidarSampling:
    """Whether a cloud was sampled by a lidar (rings of returns at regular angular steps).

    Attributes
    ----------
    twin_share : float
        Share of the examined points with two neighbours at the same distance (within
        :data:`TWIN_TOLERANCE`) on opposite sides.
    spacing_spread : float
        90th over 10th percentile of the examined points' nearest-neighbour distances.
    n_points : int
        Points examined.
    noise_ratio : float
        Median over the examined points of the RMS distance of their
        :data:`PLANE_NEIGHBOURS` nearest neighbours to their best plane, over their
        nearest-neighbour distance: the points' noise against their spacing, which grows with
        the density at a fixed range noise.
    """

    twin_share: float
    spacing_spread: float
    n_points: int
    noise_ratio: float = 0.0

    @property
    def twin_share_needed(self) -> float:
        """The twin share a lidar's sampling shows at least, at this noise ratio."""
        noisy = (self.noise_ratio - QUIET_NOISE_RATIO) / (NOISY_NOISE_RATIO - QUIET_NOISE_RATIO)
        fall = (MIN_TWIN_SHARE - MIN_NOISY_TWIN_SHARE) * min(max(noisy, 0.0), 1.0)
        return MIN_TWIN_SHARE - fall

    @property
    def lidar_like(self) -> bool:
        """Sampled by one or more lidars (not uniform, random nor gridded)."""
        return (
            self.twin_share >= self.twin_share_needed and self.spacing_spread >= MIN_SPACING_SPREAD
        )

    def evidence(self) -> dict[str, float]:
        """The figures as evidence entries (floats)."""
        return {
            "lidar_twin_share": round(self.twin_share, 4),
            "lidar_spacing_spread": round(self.spacing_spread, 3),
            "lidar_noise_ratio": round(self.noise_ratio, 3),
            "lidar_like": float(self.lidar_like),
        }


def lidar_sampling(
    points: NDArray[np.float64], *, random_state: int | np.random.Generator | None = 0
) -> LidarSampling:
    """Measure whether ``points`` were sampled by lidars, from neighbour patterns alone.

    Along a lidar's ring the returns follow each other at one angular step, so a return's
    neighbours before and after it on the ring lie at nearly the same distance on opposite
    sides, whatever the station (its own returns are the densest near it), the range or the
    merging of stations; points drawn at random have such twins by chance only.  Tens of
    milliseconds at 1M points.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    random_state : int, Generator or None

    Returns
    -------
    LidarSampling
        Zeros for clouds too small to tell (under :data:`SAMPLING_NEIGHBOURS` + 2 points).
    """
    rng = np.random.default_rng(random_state)
    points = np.asarray(points, dtype=np.float64)
    if not np.isfinite(points).all():  # one test of all values; no copy of a finite cloud
        points = points[np.isfinite(points).all(axis=1)]
    points = whole_voxels(points, SAMPLING_MAX_POINTS, rng)
    if points.shape[0] < SAMPLING_NEIGHBOURS + 2:
        return LidarSampling(0.0, 0.0, int(points.shape[0]))
    queries = points
    if points.shape[0] > SAMPLING_QUERIES:
        queries = points[rng.choice(points.shape[0], SAMPLING_QUERIES, replace=False)]
    neighbours = min(max(SAMPLING_NEIGHBOURS, PLANE_NEIGHBOURS), points.shape[0] - 1)
    distance, index = KDTree(points).query(queries, k=neighbours + 1)
    noise_ratio = _noise_ratio(points[index[:, 1:]] - queries[:, None, :], distance[:, 1])
    distance, index = (
        distance[:, 1 : SAMPLING_NEIGHBOURS + 1],
        index[:, 1 : SAMPLING_NEIGHBOURS + 1],
    )
    offset = points[index] - queries[:, None, :]
    twins = np.zeros(queries.shape[0], dtype=bool)
    for first in range(SAMPLING_NEIGHBOURS):
        for second in range(first + 1, SAMPLING_NEIGHBOURS):
            near, far = distance[:, first], distance[:, second]
            product = np.maximum(near * far, 1e-300)
            cosine = np.einsum("ij,ij->i", offset[:, first], offset[:, second]) / product
            twins |= (
                (near > 0) & (far - near <= TWIN_TOLERANCE * near) & (cosine <= OPPOSITE_COSINE)
            )
    nearest = distance[:, 0][distance[:, 0] > 0]
    spread = 0.0
    if nearest.size >= 10:
        low, high = np.quantile(nearest, [0.1, 0.9])
        spread = float(high / low) if low > 0 else math.inf
    return LidarSampling(float(twins.mean()), spread, int(queries.shape[0]), noise_ratio)


def _noise_ratio(offset: NDArray[np.float64], nearest: NDArray[np.float64]) -> float:
    """Median of the neighbours' RMS distance to their best plane over the nearest distance.

    Parameters
    ----------
    offset : ndarray, shape (q, k, 3)
        Each examined point's ``k`` nearest neighbours, relative to it.
    nearest : ndarray, shape (q,)
        Each examined point's nearest-neighbour distance.
    """
    centred = offset - offset.mean(axis=1, keepdims=True)
    covariance = np.einsum("qki,qkj->qij", centred, centred) / offset.shape[1]
    thickness = np.sqrt(np.maximum(np.linalg.eigvalsh(covariance)[:, 0], 0.0))
    valid = nearest > 0
    if not valid.any():
        return 0.0
    return float(np.median(thickness[valid] / nearest[valid]))
