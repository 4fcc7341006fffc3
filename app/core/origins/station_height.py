"""The height of a lidar station whose top-view position is known, from its rings.

From the right origin a spinning lidar's returns lie on a few cones of fixed elevation (its
rings): histogrammed by elevation, they pile up in a few narrow bins.  Seen from a height a
little off, each ring's returns spread with their horizontal distance (by ``dz / rho``
radians).  :func:`station_height` scores candidate heights by the share of points on ring
bins (:func:`ring_scores`), coarse to fine.  Used by
:func:`~app.core.origins.station_recovery.recover_stations`.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from app.core.localise.station_assignment import RING_CONTRAST, SMOOTHING_BINS

__all__ = ["HEIGHT_REACH", "ring_scores", "station_height"]

HEIGHT_SAMPLE = 40_000
"""Points (a seeded random share of those within :data:`HEIGHT_REACH`) the search uses."""
HEIGHT_COARSE_SAMPLE = 4_000
"""Points the 2 mm pass scores heights on (the first of the sample)."""
SCOUT_STEP = 0.008
"""The scouting pass's height step (metres).  A ring's score falls off within a few
millimetres of the true height, but stays among the best few local maxima: over 36 searches
of nine 1M-point merged surveys, 6-10 mm steps with the best eight maxima looked at again
found every height that 2 mm steps over the whole range find (farther returns alone, where a
ring blurs least per millimetre, found a third of them wrong)."""
SCOUT_CANDIDATES = 8
"""Best scouting heights (local maxima) looked at again in 2 mm steps."""
SCOUT_SPAN = 0.012
"""Each is looked at again within this many metres."""
HEIGHT_CHUNK = 16
"""Candidate heights histogrammed at once: 16 keep the 32-bit bins to a few hundred kilobytes
(64 at once spent a third of the search on fresh memory for them)."""
HEIGHT_REACH = 8.0
"""Only points within this many metres (top view) of the station are used."""
SURFACE_CLEARANCE = 0.3
"""A station is searched at least this far above the lowest and below the highest points."""
COARSE_BIN_DEG = 0.04
SCOUT_BINS_DEG = (COARSE_BIN_DEG, 0.01)
"""Elevation bins (degrees) the height range is scouted with, each in turn: 0.04 degree bins
blur a ring less per millimetre of height, but see none of a dense station's rings (a 100M
point survey of five stations is scanned every 0.043 degrees: its rings fill each bin alike,
and the scouted heights came out 0.4-4.5 m wrong on 7 of its 10 stations)."""
FINE_BIN_DEG = 0.01
FINE_STEP = 2e-4
FINE_SPAN = 4e-3
"""The fine pass: :data:`FINE_STEP` steps within this many metres of the best 2 mm height,
on every sampled point."""


def ring_scores(
    rho: NDArray[np.float64], z: NDArray[np.float64], heights: NDArray[np.float64], bin_size: float
) -> NDArray[np.float64]:
    """For each candidate height, the share of points whose elevation bin is on a ring.

    A bin is on a ring when its count is at least :data:`RING_CONTRAST` times the moving
    average of :data:`SMOOTHING_BINS` bins around it.

    The bins are counted in 32-bit integers (a count is at most the number of points): the
    search spends most of its time on the bins, not on the points, and 64-bit ones took
    twice as long.

    Parameters
    ----------
    rho, z : ndarray, shape (n,)
        Horizontal distance of each point from the station's axis, and its height.
    heights : ndarray, shape (h,)
        Candidate station heights.
    bin_size : float
        Elevation bin (radians).

    Returns
    -------
    ndarray, shape (h,)
    """
    n_bins = int(math.pi / bin_size) + 2
    half = SMOOTHING_BINS // 2
    # each height's row: half + 1 empty bins, its n_bins, half empty bins (the moving window
    # sees zeros beyond the ends)
    width = n_bins + SMOOTHING_BINS + 1
    contrast = np.int32(RING_CONTRAST) if float(RING_CONTRAST).is_integer() else RING_CONTRAST
    scores = np.empty(heights.size)
    # single precision: a bin is 1.7e-4 rad at the finest, far above float32's rounding
    rho32, z32 = rho.astype(np.float32), z.astype(np.float32)
    scale = np.float32(1.0 / bin_size)
    shift = np.float32(math.pi / 2 / bin_size)
    for start in range(0, heights.size, HEIGHT_CHUNK):
        part = heights[start : start + HEIGHT_CHUNK].astype(np.float32)
        elevation = np.arctan2(z32[None, :] - part[:, None], rho32[None, :])
        bins = (elevation * scale + shift).astype(np.int32)  # elevations are >= -pi/2
        bins += (np.arange(part.size, dtype=np.int32) * width + half + 1)[:, None]
        counts = np.bincount(bins.ravel(), minlength=part.size * width)
        counts = counts.astype(np.int32).reshape(part.size, width)
        cumulative = np.cumsum(counts, axis=1, dtype=np.int32)
        # bins b - half .. b + half: cumulative[b + half] - cumulative[b - half - 1]
        own = counts[:, half + 1 : half + 1 + n_bins]
        window = cumulative[:, SMOOTHING_BINS : SMOOTHING_BINS + n_bins] - cumulative[:, :n_bins]
        on_ring = own * np.int32(SMOOTHING_BINS) >= contrast * window
        ring_points = (own * on_ring).sum(axis=1, dtype=np.int32)
        scores[start : start + HEIGHT_CHUNK] = ring_points / max(rho.size, 1)
    return scores


def _local_maxima(scores: NDArray[np.float64], count: int) -> NDArray[np.int64]:
    """Indices of the ``count`` largest local maxima of ``scores`` (h,), largest first."""
    padded = np.concatenate([[-np.inf], scores, [-np.inf]])
    peak = (padded[1:-1] >= padded[:-2]) & (padded[1:-1] >= padded[2:])
    indices = np.flatnonzero(peak)
    return indices[np.argsort(-scores[indices], kind="stable")[:count]]


def station_height(
    points: NDArray[np.float64], centre: NDArray[np.float64], rng: np.random.Generator
) -> float:
    """The height of a station at top-view ``centre`` whose rings the points lie on.

    Coarse to fine, once per scouting bin of :data:`SCOUT_BINS_DEG`: a scouting pass over the
    cloud's height range (:data:`SCOUT_STEP` steps, :data:`HEIGHT_COARSE_SAMPLE` points), whose
    best :data:`SCOUT_CANDIDATES` local maxima are looked at again in 2 mm steps (the same bins
    and points); then :data:`FINE_STEP` steps round the best (0.01 degree bins, every sampled
    point).  The height whose fine score is the highest is the station's: a scouting bin as
    wide as the rings' spacing sees no rings at any height (a dense station's rings 0.04
    degrees apart fill every 0.04 degree bin alike), and the narrow one alone is noisier on
    sparse rings.  Scoring every 2 mm of the range instead found the same heights in twice
    the time.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    centre : ndarray, shape (2,)
    rng : numpy.random.Generator

    Returns
    -------
    float
    """
    horizontal = np.hypot(points[:, 0] - centre[0], points[:, 1] - centre[1])
    near = np.flatnonzero((horizontal <= HEIGHT_REACH) & (horizontal > 0.05))
    if near.size > HEIGHT_SAMPLE:
        near = rng.choice(near, HEIGHT_SAMPLE, replace=False)
    rho, z = horizontal[near], points[near, 2]
    # not at a floor's or ceiling's own height: their points would pile up at 0 degrees
    low, high = np.quantile(z, [0.01, 0.99]) + np.array([SURFACE_CLEARANCE, -SURFACE_CLEARANCE])
    if high <= low:
        low = high = float(np.median(z))
        high += 2e-3
    found = [_scouted_height(rho, z, low, high, bin_deg) for bin_deg in SCOUT_BINS_DEG]
    return max(found, key=lambda height_and_score: height_and_score[1])[0]


def coarse_sample(n_points: int) -> NDArray[np.int64]:
    """The points of the sample the scouting passes use: :data:`HEIGHT_COARSE_SAMPLE` spread
    evenly over all ``n_points`` of it (in a file's order its first points are one station's,
    and its other stations' rings were scouted on points none of them took)."""
    count = min(n_points, HEIGHT_COARSE_SAMPLE)
    return np.linspace(0, n_points - 1, count).astype(np.int64)


def _scouted_height(
    rho: NDArray[np.float64], z: NDArray[np.float64], low: float, high: float, bin_deg: float
) -> tuple[float, float]:
    """The best height between ``low`` and ``high`` scouted with ``bin_deg`` bins, and its
    score with the fine bins on every point (``rho``, ``z``: shape (n,))."""
    spread = coarse_sample(rho.size)
    coarse_rho, coarse_z = rho[spread], z[spread]
    coarse_bin = math.radians(bin_deg)
    scout_heights = np.arange(low, high, SCOUT_STEP)
    scout = ring_scores(coarse_rho, coarse_z, scout_heights, coarse_bin)
    offsets = np.arange(-SCOUT_SPAN, SCOUT_SPAN + 1e-9, 2e-3)
    candidates = np.unique(
        np.concatenate(
            [scout_heights[index] + offsets for index in _local_maxima(scout, SCOUT_CANDIDATES)]
        )
    )
    candidates = candidates[(candidates >= low - SCOUT_SPAN) & (candidates < high + SCOUT_SPAN)]
    scores = ring_scores(coarse_rho, coarse_z, candidates, coarse_bin)
    best = float(candidates[int(np.argmax(scores))])
    heights = best + np.arange(-FINE_SPAN, FINE_SPAN, FINE_STEP)
    scores = ring_scores(rho, z, heights, math.radians(FINE_BIN_DEG))
    index = int(np.argmax(scores))
    return float(heights[index]), float(scores[index])
