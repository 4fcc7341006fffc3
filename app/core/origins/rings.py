"""The lidar's height: the one from which its returns' elevations fall on a few sharp rings.

Every ring of a spinning lidar fires at one elevation, and range noise moves a return along its
ray, so from the true origin the returns' elevation angles take a few exact values.  With the
top-view centre known (:mod:`~app.core.origins.columns`), the height is found by scanning it:
the elevation histogram's sharpness (sum of squared bin shares, the probability that two returns
fall in one bin) peaks at the true height.  The share of returns in peak bins then says how much
of the cloud one upright lidar at that origin explains: nearly all of a single-station scan,
about 1/n of a cloud merged from n stations, almost none of random points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "RingFit",
    "RingOriginFit",
    "elevation_sharpness",
    "fit_ring_height",
    "ring_share",
    "sharpest_height",
]

FINE_BIN_DEG = 0.02
COARSE_BIN_DEG = 0.05
COARSE_HEIGHT_STEP = 0.01
"""The coarse height scan (far returns, :data:`COARSE_BIN_DEG` bins) steps by this (metres): a
centimetre off moves a wall's rings at 5 m by 0.1 degree, half the spacing of 0.2 degree rings;
2 cm steps with 0.1 degree bins let a height 8-16 cm off (rings aliased onto their neighbours)
win at 0.2 degree steps."""
PEAK_FACTOR = 4.0
"""A histogram bin is a ring when it holds this many times the bins' mean count."""
MIN_HORIZONTAL_RANGE = 1.0
"""Returns closer than this (metres, top view) to the axis are left out (their angle is loose)."""


@dataclass(frozen=True)
class RingFit:
    """The best height and what the elevation histogram says there.

    Attributes
    ----------
    height : float
    sharpness_gain : float
        Sharpness at ``height`` over the median sharpness of the scanned heights (>> 1 for a
        lidar's rings).
    ring_share : float
        Share of returns lying on ring bins at ``height`` (see :func:`ring_share`).
    """

    height: float
    sharpness_gain: float
    ring_share: float


def _elevation_deg(z: NDArray, horizontal: NDArray, height: float) -> NDArray[np.float64]:
    return np.rad2deg(np.arctan2(z - height, horizontal))


@dataclass(frozen=True)
class RingOriginFit:
    """An origin found on the elevation rings, with its evidence (the sharpening's and the
    apex search's result).

    Attributes
    ----------
    origin : ndarray, shape (3,)
    spike : float
        Elevation sharpness at ``origin`` over the largest of eight positions about a metre
        away (about 1 where there is no single sharp origin).
    ring_share : float
        Share of the examined returns on ring bins seen from ``origin``.
    """

    origin: NDArray[np.float64]
    spike: float
    ring_share: float


def elevation_sharpness(
    z: NDArray[np.float64], horizontal: NDArray[np.float64], height: float, bin_deg: float
) -> float:
    """Sum of squared bin shares of the elevation histogram from ``height``."""
    bins = np.floor((_elevation_deg(z, horizontal, height) + 90.0) / bin_deg).astype(np.int64)
    counts = np.bincount(bins)
    return float(np.sum(counts.astype(np.float64) ** 2) / max(len(z), 1) ** 2)


def sharpest_height(
    z: NDArray[np.float64], horizontal: NDArray[np.float64], start: float, span: float
) -> float:
    """The height within ``span`` of ``start`` from which the elevation rings are sharpest.

    Parameters
    ----------
    z, horizontal : ndarray, shape (n,)
        Heights of the returns and their horizontal distances from the candidate axis.
    start : float
        Where the search starts (m).
    span : float
        The search covers ``start +- span`` in 1 cm steps, then +-1 cm around the best in 2 mm.

    Returns
    -------
    float
        The best height (m).
    """
    best = start
    for half_width, step in ((span, 0.01), (0.01, 0.002)):
        heights = np.arange(best - half_width, best + half_width + step / 2, step)
        values = [elevation_sharpness(z, horizontal, h, FINE_BIN_DEG) for h in heights]
        best = float(heights[int(np.argmax(values))])
    return best


def ring_share(z: NDArray[np.float64], horizontal: NDArray[np.float64], height: float) -> float:
    """Share of returns in bins of :data:`FINE_BIN_DEG` holding :data:`PEAK_FACTOR` times the
    mean count of the occupied elevation span."""
    elevation = _elevation_deg(z, horizontal, height)
    bins = np.floor((elevation - elevation.min()) / FINE_BIN_DEG).astype(np.int64)
    counts = np.bincount(bins)
    mean_count = len(z) / max(len(counts), 1)
    return float(counts[counts > PEAK_FACTOR * mean_count].sum() / max(len(z), 1))


def fit_ring_height(
    points: NDArray[np.float64], centre: NDArray[np.float64], rng: np.random.Generator
) -> RingFit:
    """Scan heights over the cloud's z range for the sharpest elevation histogram.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    centre : ndarray, shape (2,)
        The lidar's top-view position.
    rng : Generator
        Draws the subsamples.
    """
    horizontal = np.linalg.norm(points[:, :2] - centre, axis=1)
    usable = points[horizontal > MIN_HORIZONTAL_RANGE]
    if len(usable) < 100:
        return RingFit(float(np.median(points[:, 2])), 1.0, 0.0)
    sample = usable[rng.choice(len(usable), size=min(len(usable), 60_000), replace=False)]
    z = sample[:, 2]
    horizontal = np.linalg.norm(sample[:, :2] - centre, axis=1)
    # coarse: far returns (angles move least per metre of height), 1 cm steps
    far = horizontal > np.quantile(horizontal, 0.5)
    low, high = np.quantile(z, [0.001, 0.999])
    heights = np.arange(low, high, COARSE_HEIGHT_STEP)
    coarse = np.array(
        [elevation_sharpness(z[far], horizontal[far], h, COARSE_BIN_DEG) for h in heights]
    )
    best = float(heights[int(np.argmax(coarse))])
    # fine: every sampled return, 2 mm then 0.5 mm steps
    for span, step in ((0.03, 0.002), (0.003, 0.0005)):
        candidates = np.arange(best - span, best + span + step / 2, step)
        fine = [elevation_sharpness(z, horizontal, h, FINE_BIN_DEG) for h in candidates]
        best = float(candidates[int(np.argmax(fine))])
    return RingFit(
        height=best,
        sharpness_gain=float(coarse.max() / max(np.median(coarse), 1e-12)),
        ring_share=ring_share(z, horizontal, best),
    )
