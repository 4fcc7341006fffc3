"""Whole-voxel subsets of a large cloud: the one rule the origin searches share.

The lidar sampling test (:mod:`app.core.origins.sampling`), the single-origin estimate
(:mod:`app.core.origins.estimate`) and the station recovery
(:mod:`app.core.origins.station_recovery`) all examine neighbour pairs, which must be the
scan's own lattice neighbours: a subset of random points would not do, so each of them takes
all the points of randomly chosen voxels.

The voxels' edge follows the cloud's density.  With a fixed edge a denser cloud fills each
voxel with more points, so a subset of fixed size holds fewer voxels: at 20M points a scan of
a warehouse, 200k points were 15 one-metre voxels (against 290 at 1M), too few places for the
column lines of five stations to concur, and no station was recovered (issue 30).  Here the
edge shrinks so that a voxel holds at most :data:`VOXEL_POINTS` points: a subset holds as many
voxels, spread over the scene as widely, at any density; each voxel still spans as many lattice
steps, since the lattice shrinks with the edge.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

__all__ = ["VOXEL_EDGE", "VOXEL_POINTS", "voxel_hash", "whole_voxels"]

VOXEL_EDGE = 1.0
"""Largest edge (metres) of the voxels a subset is made of (clouds up to :data:`VOXEL_POINTS`
points a voxel of this edge)."""
VOXEL_POINTS = 250
"""Most points (on average) a kept voxel holds; the edge shrinks below :data:`VOXEL_EDGE` for
denser clouds.  Merged 5-station warehouse surveys: 600-720 points a one-metre voxel at 1M
points a scan, about 13,000 at 20M.  Every station of them was recovered at 1M, 4M, 10M and
20M points with 250 (one or two duplicates 8-13 cm off a station at 10M and 20M with 500 and
1,000, and one station missed at 20M with 1,000)."""
VOXEL_HASH_FACTORS = (73856093, 19349663, 83492791)
"""Primes of the voxel hash (x, y, z)."""
_GOLDEN = np.int64(-7046029254386353131)  # 0x9E3779B97F4A7C15 as a signed 64-bit integer
_BUCKET_BITS = 16


def voxel_hash(points: NDArray[np.float64], cell: float) -> NDArray[np.int64]:
    """A hash of each point's ``cell``-metre voxel, shape (n,), int64.

    The xor of the voxel's integer coordinates times :data:`VOXEL_HASH_FACTORS` (wrapping
    round in 64 bits), formed column by column into reused (n,) buffers: forming the (n, 3)
    voxel coordinates in floats then integers took twice as long.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    cell : float
        Voxel edge (metres).
    """
    hashed = np.empty(points.shape[0], dtype=np.int64)
    term = np.empty(points.shape[0], dtype=np.int64)
    coordinate = np.empty(points.shape[0], dtype=np.float64)
    for axis, factor in enumerate(VOXEL_HASH_FACTORS):
        np.floor(points[:, axis] if cell == 1.0 else points[:, axis] / cell, out=coordinate)
        target = hashed if axis == 0 else term
        target[...] = coordinate  # truncation of whole floats: their value
        target *= np.int64(factor)
        if axis:
            hashed ^= term
    return hashed


def _kept(points: NDArray[np.float64], edge: float, share: float, salt: np.int64) -> NDArray:
    """Mask (n,) of the points whose ``edge``-metre voxel a seeded hash puts in the first
    ``share`` of 2**16 buckets.

    The voxel hash xor the salt, times the golden-ratio constant (wrapping), its top 16 bits:
    every bit of the voxel's key moves them (a multiplicative hash), in three passes over
    (n,) integers.
    """
    mixed = voxel_hash(points, edge)
    mixed ^= salt
    mixed *= _GOLDEN
    mixed >>= np.int64(64 - _BUCKET_BITS)  # arithmetic shift: -2**15 .. 2**15 - 1
    return mixed < -(1 << (_BUCKET_BITS - 1)) + share * (1 << _BUCKET_BITS)


def whole_voxels(
    points: NDArray[np.float64], max_points: int, rng: np.random.Generator
) -> NDArray[np.float64]:
    """About ``max_points`` of ``points`` as all the points of randomly chosen voxels.

    A voxel is kept when a seeded hash of its integer coordinates falls in the first
    ``max_points / n`` of its range, so the points inside it keep their lattice neighbours.
    The voxels are :data:`VOXEL_EDGE` metres; when those kept hold more than
    :data:`VOXEL_POINTS` points each on average, the draw is made again on voxels whose edge
    is shrunk by the square root of the excess (surfaces: points a voxel grow with its area),
    so that the subset holds as many voxels whatever the density.  One draw from ``rng``.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    max_points : int
        About how many points to keep (all of them when ``n`` is not larger).
    rng : Generator

    Returns
    -------
    ndarray, shape (m, 3)
        The kept points, in their order in ``points`` (a copy unless all are kept).
    """
    if points.shape[0] <= max_points:
        return points
    salt = np.int64(rng.integers(1, 2**62))
    share = max_points / points.shape[0]
    kept = points[_kept(points, VOXEL_EDGE, share, salt)]
    if kept.shape[0] == 0:
        return kept
    n_voxels = np.unique(voxel_hash(kept, VOXEL_EDGE)).size
    crowding = kept.shape[0] / n_voxels / VOXEL_POINTS
    if crowding <= 1.0:
        return kept
    return points[_kept(points, VOXEL_EDGE / math.sqrt(crowding), share, salt)]
