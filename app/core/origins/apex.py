"""The common apex of a spinning lidar's ring cones, searched from several starts.

Every laser of a spinning lidar sweeps a cone of one elevation about the sensor's axis, so from
the cones' apex the returns' elevations fall on a comb of sharp peaks, whatever surfaces they
hit.  The column lines (:mod:`~app.core.origins.columns`) and the sharpening
(:mod:`~app.core.origins.sharpen`) need level ground round the sensor; a frame whose ground was
removed (Lidar-SCU's Budapest HDL-64 frames: walls, trees, cars and poles only) has none, and its
column lines concur only roughly, 0.3-8 m off.  This search needs only the rings:

1. starts: the top-view points where the column lines concur best
   (:attr:`~app.core.origins.columns.ColumnFit.candidates`); one of them lies within about
   2 m of the sensor on such frames;
2. from each start, the height whose far returns fall on the sharpest rings
   (:func:`~app.core.origins.rings.fit_ring_height`: far returns move least with the top-view
   error), then alternately the height and a top-view grid round the best position, at three
   scales (0.5 m steps with 0.1 degree bins down to 2 cm steps with 0.02 degree bins).  At the
   first scale the sharpness peak is about 1 m wide in the top view and 0.2 m in height, so
   the joint search must move both; the best :data:`KEEP` starts go on to the finer scales;
3. the height reported is that of the steepest downward rays (:data:`STEEP_SHARE` of the
   returns below the apex): on an HDL-64 the lower laser block's cones meet 0.12 m above the
   sensor frame's origin, the upper block's 0.2 m (steps 1-2 fit both blocks jointly, so the
   upper one dominates); the rays that reach the ground round the sensor matter most for
   visibility;
4. the evidence: the spike (sharpness at the apex over the largest of eight positions
   :data:`SPIKE_DISTANCE` away) and the share of returns on rings from the apex.

A cloud merged from several stations has one apex per station, each explaining only its own
share of the returns (two Budapest frames merged: ring share 0.58-0.62): the confidence stays
low.  No start within about 2 m of the sensor, no apex found: the search then says so (spike
and ring share low), it does not search the whole cloud.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from app.core.origins.rings import (
    FINE_BIN_DEG,
    RingOriginFit,
    elevation_sharpness,
    fit_ring_height,
    ring_share,
    sharpest_height,
)

__all__ = ["search_apex"]

SAMPLE_POINTS = 4000
MIN_RANGE = 2.0
"""Returns closer than this (metres, top view) to a candidate are left out (the vehicle's own
body, and angles that a decimetre moves by degrees)."""
MIN_USABLE_SHARE = 0.25
"""A candidate from which fewer of the sampled returns lie beyond :data:`MIN_RANGE` scores
0: its rings would say nothing about most of the cloud (a small cloud seen from outside)."""
SCALES = (
    (2.0, 0.5, 0.4, 0.1, 0.1),
    (0.5, 0.1, 0.1, 0.02, 0.05),
    (0.1, 0.02, 0.03, 0.005, 0.02),
)
"""Per scale: top-view half-width and step, height half-width and step (metres), bin (deg)."""
ROUNDS = 2
"""Height scan then top-view grid, this many times per scale."""
KEEP = 2
"""Starts carried on past the first scale (the sharpest there)."""
SPIKE_DISTANCE = 1.0
SPIKE_BIN_DEG = FINE_BIN_DEG
DOWNWARD_HEIGHT_SPAN = 0.3
MIN_DOWNWARD = 200
STEEP_SHARE = 0.1
"""The height is fitted on this steepest share of the downward returns (at least
:data:`MIN_DOWNWARD`): the rays that reach the ground nearest the sensor (on an HDL-64 its
lower laser block; a share of the span of elevations instead would mix in the upper block's
rings on frames with few steep returns)."""
DOWNWARD_POINTS = 20_000
MIN_WALL_POINTS = 500


def _usable(sample: NDArray[np.float64], centre: NDArray) -> tuple[NDArray, NDArray[np.bool_]]:
    """Top-view distances from ``centre`` and which returns count (beyond :data:`MIN_RANGE`;
    none when fewer than :data:`MIN_USABLE_SHARE` of them are: no evidence)."""
    horizontal = np.hypot(sample[:, 0] - centre[0], sample[:, 1] - centre[1])
    usable = horizontal > MIN_RANGE
    if np.count_nonzero(usable) < max(100, MIN_USABLE_SHARE * len(sample)):
        usable[:] = False
    return horizontal, usable


def _sharpness(
    sample: NDArray[np.float64], centre: NDArray, height: float, bin_deg: float
) -> float:
    horizontal, usable = _usable(sample, centre)
    if not usable.any():
        return 0.0
    return elevation_sharpness(sample[usable, 2], horizontal[usable], height, bin_deg)


def _refine(
    sample: NDArray[np.float64],
    centre: NDArray[np.float64],
    height: float,
    scale: tuple[float, float, float, float, float],
) -> tuple[NDArray[np.float64], float, float]:
    """Alternate height scans and top-view grids at one scale; (centre, height, sharpness)."""
    xy_span, xy_step, z_span, z_step, bin_deg = scale
    offsets = np.arange(-xy_span, xy_span + xy_step / 2, xy_step)
    best = 0.0
    for _ in range(ROUNDS):
        heights = np.arange(height - z_span, height + z_span + z_step / 2, z_step)
        values = [_sharpness(sample, centre, h, bin_deg) for h in heights]
        height = float(heights[int(np.argmax(values))])
        grid = np.array(
            [
                [_sharpness(sample, centre + np.array([dx, dy]), height, bin_deg) for dy in offsets]
                for dx in offsets
            ]
        )
        row, column = np.unravel_index(int(np.argmax(grid)), grid.shape)
        centre = centre + np.array([offsets[row], offsets[column]])
        best = float(grid[row, column])
    return centre, height, best


def _downward_height(points: NDArray[np.float64], centre: NDArray, apex_height: float) -> float:
    """The height within :data:`DOWNWARD_HEIGHT_SPAN` of the apex from which the steepest
    :data:`STEEP_SHARE` of the downward returns fall on the sharpest rings (1 cm, then 2 mm
    steps)."""
    horizontal = np.hypot(points[:, 0] - centre[0], points[:, 1] - centre[1])
    usable = horizontal > MIN_RANGE
    elevation = np.arctan2(points[usable, 2] - apex_height, horizontal[usable])
    downward = np.flatnonzero(elevation < 0.0)
    count = max(MIN_DOWNWARD, int(STEEP_SHARE * len(downward)))
    if len(downward) < count:
        return apex_height
    steepest = downward[np.argsort(elevation[downward])[:count]]
    z, horizontal = points[usable, 2][steepest], horizontal[usable][steepest]
    return sharpest_height(z, horizontal, apex_height, DOWNWARD_HEIGHT_SPAN)


def search_apex(
    walls: NDArray[np.float64],
    points: NDArray[np.float64],
    starts: NDArray[np.float64],
    rng: np.random.Generator,
) -> RingOriginFit:
    """Search the ring cones' apex from top-view ``starts``.

    Parameters
    ----------
    walls : ndarray, shape (m, 3)
        Returns on surfaces facing sideways (their rings are searched: a level floor's returns
        all fall on one false ring from any point at the floor's own height).
    points : ndarray, shape (n, 3)
        The cloud (z along the lidar's axis): the downward rings' height.
    starts : ndarray, shape (k, 2)
        Top-view starting positions, e.g. the column lines' concurrence points.
    rng : Generator
        Draws the subsample.

    Returns
    -------
    RingOriginFit
        Spike 0 and ring share 0 when there are no starts or too few points.
    """
    starts = np.asarray(starts, dtype=np.float64).reshape(-1, 2)
    if len(starts) == 0 or len(walls) < MIN_WALL_POINTS:
        centre = points.mean(axis=0) if len(points) else np.zeros(3)
        return RingOriginFit(centre, 0.0, 0.0)
    sample = walls[rng.choice(len(walls), size=min(len(walls), SAMPLE_POINTS), replace=False)]
    fits = []
    for start in starts:
        height = fit_ring_height(sample, start, rng).height
        fits.append(_refine(sample, start, height, SCALES[0]))
    fits.sort(key=lambda fit: -fit[2])
    refined = []
    for centre, height, _ in fits[:KEEP]:
        for scale in SCALES[1:]:
            centre, height, value = _refine(sample, centre, height, scale)
        refined.append((centre, height, value))
    centre, height, _ = max(refined, key=lambda fit: fit[2])
    everything = points[
        rng.choice(len(points), size=min(len(points), DOWNWARD_POINTS), replace=False)
    ]
    peak = _sharpness(sample, centre, height, SPIKE_BIN_DEG)
    angles = np.linspace(0.0, 2.0 * np.pi, 8, endpoint=False)
    around = max(
        _sharpness(
            sample,
            centre + SPIKE_DISTANCE * np.array([np.cos(a), np.sin(a)]),
            height,
            SPIKE_BIN_DEG,
        )
        for a in angles
    )
    horizontal, usable = _usable(sample, centre)
    share = ring_share(sample[usable, 2], horizontal[usable], height) if usable.any() else 0.0
    return RingOriginFit(
        origin=np.array([*centre, _downward_height(everything, centre, height)]),
        spike=float(peak / max(around, 1e-12)),
        ring_share=float(share),
    )
