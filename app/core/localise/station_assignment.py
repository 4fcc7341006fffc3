"""Which station of a merged multi-station cloud took each point, given the stations' origins.

A spinning lidar's returns lie on a few cones of fixed elevation (its rings) as seen from its
own origin, and nowhere in particular as seen from any other point.  For each station the
points' elevations from its origin are histogrammed finely: bins far above the smoothed
histogram are that station's rings.  A point goes to the station in whose ring bins it lies
most clearly (the largest ratio of bin count to smoothed count); a point that fits no station's
rings goes to the nearest station (the one that sees it densest).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from app.core.localise.settings import CHUNK

__all__ = [
    "STATION_INDEX_ATTRIBUTE",
    "assign_stations",
    "best_stations",
    "elevation_bins",
    "rays_from",
    "ring_contrast",
    "station_contrasts",
]

STATION_INDEX_ATTRIBUTE = "station_index"
"""Name of the per-point attribute (int, index into the cloud's origins) of the station that
took each point of a merged cloud (a PLY/LAS extra dimension of that name)."""

ELEVATION_BIN_DEG = 0.01
"""Histogram bin of elevations: far below any lidar's ring step (0.2-1 degree)."""
SMOOTHING_BINS = 51
"""Width (bins) of the moving average that stands for the rings-free background."""
RING_CONTRAST = 3.0
"""A bin at least this many times its smoothed count is a ring bin."""
ASSIGN_CHUNK = 1 << 20
"""Points per step of :func:`assign_stations` (the result does not depend on it)."""


def rays_from(
    points: NDArray[np.float64], origins: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Unit direction (shape (m, 3)) and range (shape (m,)) of each point from its sensor
    position (``origins`` shape (3,) for one sensor, or (m, 3): one per point)."""
    offset = points - origins
    ranges = np.sqrt(np.einsum("md,md->m", offset, offset))
    return offset / np.maximum(ranges, 1e-12)[:, None], ranges


def elevation_bins(points: NDArray[np.floating], origin: NDArray[np.float64]) -> NDArray:
    """Each point's elevation from ``origin`` as a bin number, shape (n,), int64."""
    bins = np.empty(points.shape[0], dtype=np.int64)
    for start in range(0, points.shape[0], CHUNK):
        offset = np.asarray(points[start : start + CHUNK], dtype=np.float64) - origin
        horizontal = np.hypot(offset[:, 0], offset[:, 1])
        elevation = np.degrees(np.arctan2(offset[:, 2], horizontal))
        bins[start : start + CHUNK] = np.floor((elevation + 90.0) / ELEVATION_BIN_DEG)
    return bins


N_BINS = round(180.0 / ELEVATION_BIN_DEG) + 1
"""Elevation bins from -90 to 90 degrees."""


def _contrast_of_bins(counts: NDArray[np.float64]) -> NDArray[np.float64]:
    """Each elevation bin's count over the moving average of the counts around it."""
    kernel = np.ones(SMOOTHING_BINS) / SMOOTHING_BINS
    background = np.convolve(counts, kernel, mode="same")
    return counts / np.maximum(background, 1e-12)


def ring_contrast(points: NDArray[np.float64], origin: NDArray[np.float64]) -> NDArray[np.float64]:
    """How far above the background each point's elevation bin is, seen from ``origin``.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    origin : ndarray, shape (3,)

    Returns
    -------
    ndarray, shape (n,), float64
        Count of the point's elevation bin over the moving average of the counts around it:
        well above 1 for points on one of the rings of a lidar at ``origin``.
    """
    bins = np.clip(elevation_bins(points, origin), 0, N_BINS - 1)
    counts = np.bincount(bins, minlength=N_BINS).astype(np.float64)
    return _contrast_of_bins(counts)[bins]


def assign_stations(
    points: NDArray[np.floating], origins: NDArray[np.float64], dtype: type = np.int64
) -> NDArray:
    """The station that most likely took each point of a merged cloud.

    Two passes over the points, :data:`ASSIGN_CHUNK` at a time: the elevation histograms of
    every station, then each point's best station, so that memory beyond the result stays at
    one chunk whatever the cloud's size.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        float64 or float32.
    origins : ndarray, shape (k, 3)
        The stations' origins, in the points' frame.
    dtype : numpy integer type
        Of the result (a narrow one keeps a large cloud's index small: int8 for k <= 127).

    Returns
    -------
    ndarray, shape (n,), ``dtype``
        Index into ``origins``: the station on whose rings the point lies most clearly
        (contrast >= :data:`RING_CONTRAST`), else the nearest station.
    """
    origins = np.asarray(origins, dtype=np.float64)
    contrast_of_bins = station_contrasts(points, origins)
    best = np.empty(points.shape[0], dtype=dtype)
    for start in range(0, points.shape[0], ASSIGN_CHUNK):
        best[start : start + ASSIGN_CHUNK] = best_stations(
            points[start : start + ASSIGN_CHUNK], origins, contrast_of_bins
        )
    return best


def station_contrasts(
    points: NDArray[np.floating], origins: NDArray[np.float64]
) -> list[NDArray[np.float64]]:
    """The first pass of :func:`assign_stations`: each station's ring contrast per elevation
    bin, from ``points`` (shape (n, 3); a cloud streamed in chunks passes its subsample).

    Returns
    -------
    list of ndarray, shape (N_BINS,)
        One per row of ``origins`` (shape (k, 3)).
    """
    origins = np.asarray(origins, dtype=np.float64)
    counts = np.zeros((origins.shape[0], N_BINS))
    for start in range(0, points.shape[0], ASSIGN_CHUNK):
        chunk = points[start : start + ASSIGN_CHUNK]
        for number, origin in enumerate(origins):
            bins = np.clip(elevation_bins(chunk, origin), 0, N_BINS - 1)
            counts[number] += np.bincount(bins, minlength=N_BINS)
    return [_contrast_of_bins(row) for row in counts]


def best_stations(
    points: NDArray[np.floating],
    origins: NDArray[np.float64],
    contrast_of_bins: list[NDArray[np.float64]],
) -> NDArray[np.int64]:
    """The second pass of :func:`assign_stations` on one chunk ``points`` (shape (c, 3)),
    given :func:`station_contrasts`; shape (c,), int64 (a point's station does not depend on
    the chunk it is in)."""
    return _best_stations(
        np.asarray(points, dtype=np.float64),
        np.asarray(origins, dtype=np.float64),
        contrast_of_bins,
    )


def _best_stations(
    points: NDArray[np.float64], origins: NDArray[np.float64], contrast_of_bins: list[NDArray]
) -> NDArray[np.int64]:
    """:func:`assign_stations` of one chunk, given each station's contrast per bin."""
    # the best station so far and its contrast, station by station (as an argmax over the
    # stacked contrasts, the first of equal ones, without the (k, n) stack)
    best = np.zeros(points.shape[0], dtype=np.int64)
    best_contrast = contrast_of_bins[0][np.clip(elevation_bins(points, origins[0]), 0, N_BINS - 1)]
    for number in range(1, origins.shape[0]):
        bins = np.clip(elevation_bins(points, origins[number]), 0, N_BINS - 1)
        contrast = contrast_of_bins[number][bins]
        better = contrast > best_contrast
        best[better] = number
        np.maximum(best_contrast, contrast, out=best_contrast)
    # only the points on no station's rings need their nearest station
    off_rings = np.flatnonzero(best_contrast < RING_CONTRAST)
    for start in range(0, off_rings.size, CHUNK):
        part = off_rings[start : start + CHUNK]
        offset = points[part, None, :] - origins[None, :, :]
        best[part] = np.argmin(np.einsum("pkd,pkd->pk", offset, offset), 1)
    return best
