"""Where a single-station lidar scan was taken from, from its points alone.

Two steps, one signal each (see :mod:`~app.core.origins.columns` and
:mod:`~app.core.origins.rings`): the top-view centre the lidar's columns radiate from, then the
height from which the returns' elevations fall on sharp rings.  Both use only angles, which
range noise does not move, so on a single upright station the origin comes out to millimetres.

The confidence is high only when both signals say "one upright spinning lidar": most lines
concur at the centre and nearly every return lies on a ring.  Real lidars whose columns are
not half-planes are sharpened on their rings (:mod:`~app.core.origins.sharpen`, from the rough
centre, needs level ground round the sensor); when that fails too, the ring cones' apex is
searched from each point where the column lines concur (:mod:`~app.core.origins.apex`: frames
whose ground was removed).  Clouds merged from several stations, random points and tilted
sensors fail one or both and get a low confidence; the pipeline then does not use the
estimate (:data:`CONFIDENT`; a tilted cloud may be estimated in its own frame instead,
:mod:`~app.core.origins.own_frame`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from app.core.origins.apex import search_apex
from app.core.origins.columns import (
    column_lines,
    fit_column_centre,
    horizontal_bounds,
)
from app.core.origins.rings import fit_ring_height
from app.core.origins.sharpen import sharpen_origin
from app.core.origins.voxels import whole_voxels

__all__ = ["CONFIDENT", "MIN_POINTS", "OriginEstimate", "confidence_ramp", "estimate_origin"]

CONFIDENT = 0.5
"""An estimate at least this confident is used when no origin is given."""
MIN_POINTS = 2000
"""Smaller clouds get no estimate (confidence 0)."""
PATCH_POINTS = 40_000
"""Points (whole voxels, the crowded ones thinned: :func:`~app.core.origins.voxels.whole_voxels`)
whose neighbour pairs are examined."""
QUERY_POINTS = 15_000
RING_SHARE_RANGE = (0.6, 0.85)
"""Ring share mapped onto confidence 0..1 (single stations: 0.95-1; four merged: 0.1-0.6)."""
CONCURRING_RANGE = (0.04, 0.08)
"""Concurring-line share mapped onto confidence 0..1 (single stations ~0.10, four merged ~0.015)."""
SHARPEN_RING_SHARE = 0.7
"""An unconfident estimate with at least this ring share is sharpened on the rings
(:mod:`~app.core.origins.sharpen`: real lidars whose columns are not half-planes).  With the
apex search allowed, one whose column lines concur weakly (below the top of
:data:`CONCURRING_RANGE`) is sharpened whatever its ring share: a spinning lidar with a random
phase per ring or azimuth jitter has no half-plane columns either, its column centre lies
0.02-1.8 m off and its rings blur there (ring share 0.1-0.85 though 0.95-1 from the sensor)."""
SPIKE_RANGE = (1.5, 3.0)
"""Sharpened origins: elevation-sharpness spike mapped onto confidence 0..1 (KITTI HDL-64
frames 3.4-3.6; merged stations and clouds without one origin 0.6-2.6)."""
APEX_SPIKE_RANGE = (1.5, 2.5)
"""Apex searches (:mod:`~app.core.origins.apex`): wall returns' sharpness at the apex over 1 m
away mapped onto confidence 0..1 (Budapest HDL-64 frames without ground 4.3-5.4; random points
and the paper's corridor 0.9-1.05; two Budapest frames merged ~3: there the ring share tells)."""
APEX_RING_SHARE_RANGE = (0.7, 0.85)
"""Apex searches: ring share from the apex mapped onto confidence 0..1 (Budapest frames
0.85-0.95; two Budapest frames merged 0.58-0.62: the apex search finds one station's apex,
which explains only its own returns; random points 0.25)."""


@dataclass(frozen=True)
class OriginEstimate:
    """An estimated sensor origin, how far to trust it and why.

    Attributes
    ----------
    origin : ndarray, shape (3,)
        In the coordinates of the points given.
    confidence : float
        In [0, 1]; use the origin only from :data:`CONFIDENT`.
    evidence : dict
        ``concurring_share``, ``second_peak_ratio``, ``ring_share``, ``sharpness_gain``,
        ``n_points``, ``seconds``; ``sharpened_spike`` and ``sharpened_ring_share`` when the
        estimate was sharpened on the rings (:mod:`~app.core.origins.sharpen`); ``apex_spike``
        and ``apex_ring_share`` when the rings' apex was searched (:mod:`~app.core.origins.apex`).
    """

    origin: NDArray[np.float64]
    confidence: float
    evidence: dict[str, float] = field(default_factory=dict)

    @property
    def confident(self) -> bool:
        """Whether the estimate may be used (confidence >= :data:`CONFIDENT`)."""
        return self.confidence >= CONFIDENT


def confidence_ramp(value: float, bounds: tuple[float, float]) -> float:
    """0 at or below ``bounds[0]``, 1 at or above ``bounds[1]``, linear between: how one signal
    (a concurring share, a ring share, a spike) counts in an estimate's confidence."""
    low, high = bounds
    return float(np.clip((value - low) / (high - low), 0.0, 1.0))


def estimate_origin(
    points: NDArray[np.float64],
    *,
    random_state: int | np.random.Generator | None = 0,
    apex: bool = True,
) -> OriginEstimate:
    """Estimate the position of the upright spinning lidar that took ``points``.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        One cloud in any frame whose z axis is the lidar's axis (within a degree or so);
        the order of the points does not matter.
    random_state : int, Generator or None
        Seeds the subsamples (the result is deterministic for a given seed).
    apex : bool
        Search the rings' apex when the other signals leave the estimate unconfident (1-2.5 s
        at 1M points).  Off where a cloud that fails them is taken for a merged survey and its
        stations are recovered first (:func:`~app.core.origins.station_recovery.resolve_stations`).

    Returns
    -------
    OriginEstimate
        Confidence 0 for clouds under :data:`MIN_POINTS` points or without finite points.
    """
    started = time.perf_counter()
    points = np.asarray(points, dtype=np.float64)
    # no copy of a finite cloud (24 MB at 1M points); one test of all values first, 15x
    # quicker than a test of each row
    if not np.isfinite(points).all():
        points = points[np.isfinite(points).all(axis=1)]
    if len(points) < MIN_POINTS:
        centre = points.mean(axis=0) if len(points) else np.zeros(3)
        return OriginEstimate(centre, 0.0, {"n_points": float(len(points)), "seconds": 0.0})
    rng = np.random.default_rng(random_state)
    patch = whole_voxels(points, PATCH_POINTS, rng, thin_crowded=True)
    anchor, direction, wall_points = column_lines(patch, QUERY_POINTS, rng)
    low, high = horizontal_bounds(points)
    columns = fit_column_centre(anchor, direction, low, high)
    rings = fit_ring_height(wall_points, columns.centre, rng)
    confidence = min(
        confidence_ramp(columns.concurring_share, CONCURRING_RANGE),
        confidence_ramp(rings.ring_share, RING_SHARE_RANGE),
    )
    evidence = {
        "concurring_share": columns.concurring_share,
        "second_peak_ratio": columns.second_peak_ratio,
        "ring_share": rings.ring_share,
        "sharpness_gain": rings.sharpness_gain,
        "n_points": float(len(points)),
    }
    origin = np.array([*columns.centre, rings.height])
    # columns that concur only roughly leave the centre decimetres to a metre off, where the
    # rings blur whatever the lidar: their ring share there says nothing, so the sharpening
    # (0.3-0.8 s) is tried before the apex search (1-2.5 s) would be
    weak_columns = columns.concurring_share < CONCURRING_RANGE[1]
    if confidence < CONFIDENT and (
        rings.ring_share >= SHARPEN_RING_SHARE or (apex and weak_columns)
    ):
        sharpened = sharpen_origin(points, patch, origin, rng)
        sharpened_confidence = min(
            confidence_ramp(sharpened.ring_share, RING_SHARE_RANGE),
            confidence_ramp(sharpened.spike, SPIKE_RANGE),
        )
        evidence["sharpened_spike"] = sharpened.spike
        evidence["sharpened_ring_share"] = sharpened.ring_share
        if sharpened_confidence > confidence:
            origin, confidence = sharpened.origin, sharpened_confidence
    if apex and confidence < CONFIDENT:
        found = search_apex(wall_points, points, columns.candidates, rng)
        apex_confidence = min(
            confidence_ramp(found.ring_share, APEX_RING_SHARE_RANGE),
            confidence_ramp(found.spike, APEX_SPIKE_RANGE),
        )
        evidence["apex_spike"] = found.spike
        evidence["apex_ring_share"] = found.ring_share
        if apex_confidence > confidence:
            origin, confidence = found.origin, apex_confidence
    evidence["seconds"] = time.perf_counter() - started
    return OriginEstimate(origin=origin, confidence=confidence, evidence=evidence)
