"""Which station of a merged multi-station cloud took each point, given the stations' origins.

A spinning lidar's returns lie on a few cones of fixed elevation (its rings) as seen from its
own origin, and nowhere in particular as seen from any other point.  For each station the
points' elevations from its origin are histogrammed finely: bins far above the smoothed
histogram are that station's rings.  A scanner that fires at fixed azimuth steps (a terrestrial
scanner's vertical profiles) also puts its returns on a few half-planes through its vertical
axis (its columns), histogrammed the same way by azimuth.  A point's grid contrast from a
station is the product of its ring and column contrasts, each at least 1 (no structure is no
evidence against): on a station's ring *and* column it is far above any chance alignment with
one of another station's rings (TLS 2004: returns a near station took, whose elevation its
thinning blurred, lay on a far station's ring; with the columns 4,639 -> 913 misassigned
returns in the reference, 5,685 -> 1,919 in the scan).  A point goes to the station of the
largest grid contrast; a point that fits no station's grid goes to the nearest station (the one
that sees it densest).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from app.core.localise.settings import CHUNK

__all__ = [
    "STATION_INDEX_ATTRIBUTE",
    "StationGrid",
    "assign_stations",
    "azimuth_bins",
    "best_stations",
    "elevation_bins",
    "grid_contrast",
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
AZIMUTH_BIN_DEG = 0.01
"""Histogram bin of azimuths: far below any scanner's column step."""
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
N_AZIMUTH_BINS = round(360.0 / AZIMUTH_BIN_DEG)
"""Azimuth bins from -180 to 180 degrees (a circle)."""


class StationGrid(NamedTuple):
    """One station's contrast per elevation bin (its rings) and per azimuth bin (its columns)."""

    elevation: NDArray[np.float64]
    """Shape (N_BINS,)."""
    azimuth: NDArray[np.float64]
    """Shape (N_AZIMUTH_BINS,)."""

    def packed(self) -> NDArray[np.float64]:
        """Both in one row, shape (N_BINS + N_AZIMUTH_BINS,) (to save with a pass)."""
        return np.concatenate([self.elevation, self.azimuth])

    @classmethod
    def of_packed(cls, row: NDArray[np.float64]) -> StationGrid:
        """The grid of a :meth:`packed` row."""
        return cls(row[:N_BINS], row[N_BINS:])


def azimuth_bins(points: NDArray[np.floating], origin: NDArray[np.float64]) -> NDArray:
    """Each point's azimuth about ``origin`` as a bin number, shape (n,), int64."""
    bins = np.empty(points.shape[0], dtype=np.int64)
    for start in range(0, points.shape[0], CHUNK):
        offset = np.asarray(points[start : start + CHUNK], dtype=np.float64) - origin
        azimuth = np.degrees(np.arctan2(offset[:, 1], offset[:, 0]))
        bins[start : start + CHUNK] = np.floor((azimuth + 180.0) / AZIMUTH_BIN_DEG)
    return bins % N_AZIMUTH_BINS


def _contrast_of_azimuths(counts: NDArray[np.float64]) -> NDArray[np.float64]:
    """:func:`_contrast_of_bins` of a circle of azimuth bins (the average wraps around)."""
    pad = SMOOTHING_BINS
    wrapped = np.concatenate([counts[-pad:], counts, counts[:pad]])
    return _contrast_of_bins(wrapped)[pad:-pad]


def grid_contrast(
    points: NDArray[np.floating], origin: NDArray[np.float64], grid: StationGrid
) -> NDArray[np.float64]:
    """How clearly each point (shape (n, 3)) lies on the rings and columns of the station at
    ``origin`` (``grid``: its :func:`station_contrasts`), shape (n,): the product of its ring
    and column contrasts, each taken at least 1."""
    ring = grid.elevation[np.clip(elevation_bins(points, origin), 0, N_BINS - 1)]
    column = grid.azimuth[azimuth_bins(points, origin)]
    return np.maximum(ring, 1.0) * np.maximum(column, 1.0)


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
        Index into ``origins``: the station on whose rings and columns the point lies most
        clearly (:func:`grid_contrast` >= :data:`RING_CONTRAST`), else the nearest station.
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
) -> list[StationGrid]:
    """The first pass of :func:`assign_stations`: each station's ring contrast per elevation
    bin and column contrast per azimuth bin, from ``points`` (shape (n, 3); a cloud streamed in
    chunks passes its subsample).

    Returns
    -------
    list of StationGrid
        One per row of ``origins`` (shape (k, 3)).
    """
    origins = np.asarray(origins, dtype=np.float64)
    counts = np.zeros((origins.shape[0], N_BINS))
    columns = np.zeros((origins.shape[0], N_AZIMUTH_BINS))
    for start in range(0, points.shape[0], ASSIGN_CHUNK):
        chunk = points[start : start + ASSIGN_CHUNK]
        for number, origin in enumerate(origins):
            bins = np.clip(elevation_bins(chunk, origin), 0, N_BINS - 1)
            counts[number] += np.bincount(bins, minlength=N_BINS)
            columns[number] += np.bincount(azimuth_bins(chunk, origin), minlength=N_AZIMUTH_BINS)
    return [
        StationGrid(_contrast_of_bins(row), _contrast_of_azimuths(column))
        for row, column in zip(counts, columns, strict=True)
    ]


def best_stations(
    points: NDArray[np.floating],
    origins: NDArray[np.float64],
    contrast_of_bins: list[StationGrid],
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
    points: NDArray[np.float64], origins: NDArray[np.float64], contrast_of_bins: list[StationGrid]
) -> NDArray[np.int64]:
    """:func:`assign_stations` of one chunk, given each station's contrast per bin."""
    # the best station so far and its contrast, station by station (as an argmax over the
    # stacked contrasts, the first of equal ones, without the (k, n) stack)
    best = np.zeros(points.shape[0], dtype=np.int64)
    best_contrast = grid_contrast(points, origins[0], contrast_of_bins[0])
    for number in range(1, origins.shape[0]):
        contrast = grid_contrast(points, origins[number], contrast_of_bins[number])
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
