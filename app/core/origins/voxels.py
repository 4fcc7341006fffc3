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

__all__ = [
    "CROWDED_POINTS",
    "VOXEL_EDGE",
    "VOXEL_POINTS",
    "WholeVoxelSample",
    "voxel_hash",
    "whole_voxels",
]

VOXEL_EDGE = 1.0
"""Largest edge (metres) of the voxels a subset is made of (clouds up to :data:`VOXEL_POINTS`
points a voxel of this edge)."""
VOXEL_POINTS = 250
"""Most points (on average) a kept voxel holds; the edge shrinks below :data:`VOXEL_EDGE` for
denser clouds.  Merged 5-station warehouse surveys: 600-720 points a one-metre voxel at 1M
points a scan, about 13,000 at 20M.  Every station of them was recovered at 1M, 4M, 10M and
20M points with 250 (one or two duplicates 8-13 cm off a station at 10M and 20M with 500 and
1,000, and one station missed at 20M with 1,000)."""
CROWDED_POINTS = 1_200
"""A kept voxel holding more points than this is thinned to :data:`VOXEL_POINTS` when asked
(:func:`whole_voxels` with ``thin_crowded``).  The real KITTI HDL-64 frames hold at most 982-1,167
points a one-metre voxel (their near ground; a Budapest frame 2,218), a car-sized box of grid
points added to one 1,480-3,400.  Bounds of 250 and 1,000 thinned the KITTI frames' own near
voxels too, and the new draw put the ring share of frame1, tilted by the alignment, under the
own-frame retry's bound: its origin was lost (KITTI pair 0-1: 266 -> 1,093 changed points)."""
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
    count = points.shape[0]
    hashed = np.empty(count, dtype=np.int64)
    # a block of rows at a time through small reused buffers: (n,) temporaries of a 1M-point
    # cloud were fresh mappings whose pages faulted in, six clouds' worth a comparison
    rows = min(HASH_BLOCK_ROWS, count)
    term = np.empty(rows, dtype=np.int64)
    coordinate = np.empty(rows, dtype=np.float64)
    for start in range(0, count, HASH_BLOCK_ROWS):
        block = slice(start, start + HASH_BLOCK_ROWS)
        size = min(HASH_BLOCK_ROWS, count - start)
        for axis, factor in enumerate(VOXEL_HASH_FACTORS):
            column = points[block, axis]
            if cell == 1.0:
                np.floor(column, out=coordinate[:size])
            else:
                np.divide(column, cell, out=coordinate[:size])
                np.floor(coordinate[:size], out=coordinate[:size])
            target = hashed[block] if axis == 0 else term[:size]
            target[...] = coordinate[:size]  # truncation of whole floats: their value
            target *= np.int64(factor)
            if axis:
                hashed[block] ^= target
    return hashed


HASH_BLOCK_ROWS = 1 << 15
"""Rows :func:`voxel_hash` forms at once (0.25 MiB a buffer, under the 1 MiB mmap threshold of
``app.kit.allocator``)."""


def _voxel_draws(points: NDArray[np.float64], edge: float, salt: np.int64) -> NDArray[np.int64]:
    """A seeded random 64-bit draw per ``edge``-metre voxel, for each point, shape (n,).

    The voxel hash xor the salt, times the golden-ratio constant (wrapping): every bit of the
    voxel's key moves the top bits (a multiplicative hash), in three passes over (n,) integers.
    One-to-one with the voxel hash: equal draws are one voxel.
    """
    mixed = voxel_hash(points, edge)
    mixed ^= salt
    mixed *= _GOLDEN
    return mixed


def _drawn(mixed: NDArray[np.int64], share: float) -> NDArray[np.bool_]:
    """Mask of the draws whose top 16 bits fall in the first ``share`` of 2**16 buckets."""
    bucket = mixed >> np.int64(64 - _BUCKET_BITS)  # arithmetic shift: -2**15 .. 2**15 - 1
    return bucket < -(1 << (_BUCKET_BITS - 1)) + share * (1 << _BUCKET_BITS)


def _thinned(
    points: NDArray[np.float64], mixed: NDArray[np.int64], edge: float
) -> NDArray[np.bool_]:
    """Mask (m,) of the drawn ``points`` (m, 3) kept once the crowded voxels are thinned.

    A voxel (draws ``mixed`` (m,) of :func:`_voxel_draws`, ``edge`` metres) holding ``count`` >
    :data:`CROWDED_POINTS` points is cut into sub-voxels of the edge shrunk by the square root
    of ``count / VOXEL_POINTS`` (surfaces: about :data:`VOXEL_POINTS` points each), and each is
    kept with probability ``VOXEL_POINTS / count``: the voxel weighs :data:`VOXEL_POINTS`
    points on average, and its kept part is still whole sub-voxels of lattice neighbours.
    """
    _, inverse, counts = np.unique(mixed, return_inverse=True, return_counts=True)
    count = counts[inverse]
    keep = count <= CROWDED_POINTS
    crowded = np.flatnonzero(~keep)
    if crowded.size:
        crowd = count[crowded]
        sub_edge = edge / np.sqrt(crowd / VOXEL_POINTS)
        sub = voxel_hash(points[crowded] / sub_edge[:, None], 1.0)
        sub ^= mixed[crowded]
        sub *= _GOLDEN
        uniform = (sub >> np.int64(32)) & np.int64(0xFFFFFFFF)  # top 32 bits
        keep[crowded] = uniform * crowd < np.int64(VOXEL_POINTS) << np.int64(32)
    return keep


def whole_voxels(
    points: NDArray[np.float64],
    max_points: int,
    rng: np.random.Generator,
    *,
    thin_crowded: bool = False,
) -> NDArray[np.float64]:
    """About ``max_points`` of ``points`` as all the points of randomly chosen voxels.

    A voxel is kept when a seeded hash of its integer coordinates falls in the first
    ``max_points / n`` of its range, so the points inside it keep their lattice neighbours.
    The voxels are :data:`VOXEL_EDGE` metres; when those kept hold more than
    :data:`VOXEL_POINTS` points each on average, the draw is made again on voxels whose edge
    is shrunk by the square root of the excess (surfaces: points a voxel grow with its area),
    so that the subset holds as many voxels whatever the density.  One draw from ``rng``.

    With ``thin_crowded``, a kept voxel far denser than that (more than :data:`CROWDED_POINTS`
    points) is thinned to whole sub-voxels of it weighing :data:`VOXEL_POINTS` points on
    average (:func:`_thinned`), so the subset follows space rather than point counts where they
    part: for the single-origin estimate, whose column lines and ring share count points, and
    which an object sampled far more densely than the lidar sampled anything (a car-sized box
    of 39k grid points added to a 120k-point KITTI frame: 1,500-3,400 points a one-metre voxel
    where the lidar's own hold at most ~980) would otherwise outweigh.  The subset is then
    smaller than ``max_points`` by the points thinned out.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    max_points : int
        About how many points to keep (all of them when ``n`` is not larger).
    rng : Generator
    thin_crowded : bool
        Thin the voxels holding more than :data:`CROWDED_POINTS` points.

    Returns
    -------
    ndarray, shape (m, 3)
        The kept points, in their order in ``points`` (a copy unless all are kept).
    """
    if points.shape[0] <= max_points:
        return points
    salt = np.int64(rng.integers(1, 2**62))
    share = max_points / points.shape[0]
    mixed = _voxel_draws(points, VOXEL_EDGE, salt)
    drawn = _drawn(mixed, share)
    if not drawn.any():
        return points[drawn]
    kept_draws = mixed[drawn]
    crowding = kept_draws.shape[0] / np.unique(kept_draws).size / VOXEL_POINTS
    edge = VOXEL_EDGE
    if crowding > 1.0:
        edge = VOXEL_EDGE / math.sqrt(crowding)
        mixed = _voxel_draws(points, edge, salt)
        drawn = _drawn(mixed, share)
    if not thin_crowded:
        return points[drawn]
    kept = np.flatnonzero(drawn)
    return points[kept[_thinned(points[kept], mixed[kept], edge)]]


SAMPLE_EDGES = tuple(VOXEL_EDGE / 2.0**power for power in range(8))
"""Voxel edges a streamed sample is drawn at, all at once (1 m down to 7.8 mm: up to about
16,000 times :data:`VOXEL_POINTS` points a one-metre voxel, 100M-point surveys included)."""


class WholeVoxelSample:
    """:func:`whole_voxels` of a cloud read a chunk at a time: about ``max_points`` of its
    points, all those of randomly chosen voxels, never holding the cloud.

    Each chunk's points are drawn at every edge of :data:`SAMPLE_EDGES` (a seeded hash of their
    voxel, as :func:`whole_voxels` draws them); :meth:`points` keeps the draw at the largest
    edge whose voxels hold at most :data:`VOXEL_POINTS` points on average (whole voxels of
    lattice neighbours at any density: what the lidar sampling test needs of a cloud that the
    comparison only sees subsampled, :mod:`app.core.tiling.streamed`).

    Parameters
    ----------
    n_points : int
        Points of the whole cloud (its rows: an upper bound is fine).
    max_points : int
    random_state : int
    """

    def __init__(self, n_points: int, max_points: int, random_state: int = 0) -> None:
        self.share = min(1.0, max_points / max(1, n_points))
        self.salt = np.int64(np.random.default_rng(random_state).integers(1, 2**62))
        self._points: list[list[NDArray[np.float64]]] = [[] for _ in SAMPLE_EDGES]
        self._draws: list[list[NDArray[np.int64]]] = [[] for _ in SAMPLE_EDGES]

    def add(self, points: NDArray[np.floating]) -> None:
        """Draw the voxels of a chunk of the cloud, shape (c, 3) (any frame, the same for all
        chunks)."""
        points = np.asarray(points, dtype=np.float64)
        for number, edge in enumerate(SAMPLE_EDGES):
            mixed = _voxel_draws(points, edge, self.salt)
            drawn = _drawn(mixed, self.share)
            self._points[number].append(points[drawn])
            self._draws[number].append(mixed[drawn])

    def points(self) -> NDArray[np.float64]:
        """The sample, shape (m, 3): the draw at the largest edge not crowded."""
        chosen = len(SAMPLE_EDGES) - 1
        for number in range(len(SAMPLE_EDGES)):
            draws = np.concatenate(self._draws[number]) if self._draws[number] else None
            if draws is None or not len(draws):
                continue
            if len(draws) / np.unique(draws).size <= VOXEL_POINTS:
                chosen = number
                break
        parts = self._points[chosen]
        return np.concatenate(parts) if parts else np.zeros((0, 3))
