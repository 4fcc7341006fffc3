"""Multi-station ray-cast scenes: 3-5 lidar stations per epoch, merged and shuffled.

The building, furniture and changing boxes are those of :func:`app.core.synthetic.raycast_scene`
(16 x 8 x 3 m, two rooms); the lidar here has the issue's field of view (elevation -45 to 60
degrees, so a blind disc under each station), rings ``ring_step_deg`` apart.  Epoch 2's
stations are epoch 1's moved 0.1-1.5 m.  Truth: a point is changed when it lies on a changing
box; observed when some station of the other epoch sees it (in range, in view, not occluded in
the other world).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from app.core.synthetic import (
    ROOM_MAX,
    ROOM_MIN,
    STATIC_BOXES,
    _box_arrays,
    _cast_rays,
    raycast_scene_objects,
)

ELEVATION_DEG = (-45.0, 60.0)
MAX_RANGE = 40.0
CLEARANCE = 0.6


@dataclass(frozen=True)
class StationPair:
    """Two merged multi-station clouds of one site (world frame) and their truth."""

    reference: NDArray[np.float64]
    scan: NDArray[np.float64]
    reference_origins: NDArray[np.float64]  # (k, 3)
    scan_origins: NDArray[np.float64]  # (l, 3)
    reference_station: NDArray[np.int64]  # (n,)
    scan_station: NDArray[np.int64]  # (m,)
    reference_changed: NDArray[np.bool_]
    scan_changed: NDArray[np.bool_]
    reference_observed: NDArray[np.bool_]
    scan_observed: NDArray[np.bool_]


def _directions(ring_step_deg: float, azimuth_step_deg: float, rng) -> NDArray[np.float64]:
    low, high = ELEVATION_DEG
    elevation = np.arange(low + ring_step_deg / 2, high, ring_step_deg)
    azimuth = np.arange(0.0, 360.0, azimuth_step_deg)
    phase = rng.uniform(0.0, azimuth_step_deg)
    el, az = np.meshgrid(np.deg2rad(elevation), np.deg2rad(azimuth + phase), indexing="ij")
    el, az = el.ravel(), az.ravel()
    return np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def _free(position, boxes) -> bool:
    low, high = _box_arrays(boxes)
    inside = np.all(position > ROOM_MIN + CLEARANCE) and np.all(position < ROOM_MAX - CLEARANCE)
    gap = np.maximum(np.maximum(low - position, position - high), 0.0)
    return bool(inside and np.linalg.norm(gap, axis=1).min() >= CLEARANCE)


def _stations(n_stations: int, boxes, rng) -> NDArray[np.float64]:
    chosen: list[NDArray[np.float64]] = []
    while len(chosen) < n_stations:
        candidate = np.array([rng.uniform(1.0, 15.0), rng.uniform(1.0, 7.0), rng.uniform(0.8, 1.5)])
        if _free(candidate, boxes) and all(np.linalg.norm(candidate - c) > 2.5 for c in chosen):
            chosen.append(candidate)
    return np.array(chosen)


def _moved(origins, boxes, rng) -> NDArray[np.float64]:
    moved = []
    for origin in origins:
        while True:
            shift = rng.uniform(0.1, 1.5)
            heading = rng.uniform(0.0, 2 * np.pi)
            candidate = origin + shift * np.array([np.cos(heading), np.sin(heading), 0.0])
            candidate[2] = rng.uniform(0.8, 1.5)
            if _free(candidate, boxes):
                moved.append(candidate)
                break
    return np.array(moved)


def _seen_by_any(origins, points, low, high) -> NDArray[np.bool_]:
    seen = np.zeros(points.shape[0], dtype=bool)
    for origin in origins:
        offset = points - origin
        distance = np.linalg.norm(offset, axis=1)
        direction = offset / distance[:, None]
        elevation = np.rad2deg(np.arcsin(np.clip(direction[:, 2], -1, 1)))
        in_view = (
            (distance <= MAX_RANGE)
            & (elevation >= ELEVATION_DEG[0])
            & (elevation <= ELEVATION_DEG[1])
        )
        hit, _ = _cast_rays(origin, direction, low, high)
        seen |= in_view & (hit >= distance - 1e-6)
    return seen


def multistation_scene(
    *,
    change: str = "box",
    n_stations: int = 4,
    ring_step_deg: float = 0.5,
    azimuth_step_deg: float = 0.25,
    range_noise: float = 0.01,
    seed: int = 0,
) -> StationPair:
    """Two epochs of ``n_stations`` stations each, merged and shuffled (world frame)."""
    rng = np.random.default_rng(seed)
    reference_only, scan_only = raycast_scene_objects(change)
    all_boxes = [*STATIC_BOXES, *reference_only, *scan_only]
    reference_origins = _stations(n_stations, all_boxes, rng)
    scan_origins = _moved(reference_origins, all_boxes, rng)
    worlds = {
        "reference": _box_arrays([*STATIC_BOXES, *reference_only]),
        "scan": _box_arrays([*STATIC_BOXES, *scan_only]),
    }
    n_static = len(STATIC_BOXES)
    clouds = {}
    for name, origins in (("reference", reference_origins), ("scan", scan_origins)):
        low, high = worlds[name]
        exact, noisy, station, changed = [], [], [], []
        for number, origin in enumerate(origins):
            direction = _directions(ring_step_deg, azimuth_step_deg, rng)
            distance, hit = _cast_rays(origin, direction, low, high)
            keep = distance <= MAX_RANGE
            direction, distance, hit = direction[keep], distance[keep], hit[keep]
            exact.append(origin + distance[:, None] * direction)
            ranged = distance + rng.normal(0.0, range_noise, distance.shape)
            noisy.append(origin + ranged[:, None] * direction)
            station.append(np.full(distance.shape[0], number, dtype=np.int64))
            changed.append(hit >= n_static)
        order = rng.permutation(sum(part.shape[0] for part in exact))
        clouds[name] = tuple(
            np.concatenate(part)[order] for part in (exact, noisy, station, changed)
        )
    reference_exact, reference, reference_station, reference_changed = clouds["reference"]
    scan_exact, scan, scan_station, scan_changed = clouds["scan"]
    return StationPair(
        reference=reference,
        scan=scan,
        reference_origins=reference_origins,
        scan_origins=scan_origins,
        reference_station=reference_station,
        scan_station=scan_station,
        reference_changed=reference_changed,
        scan_changed=scan_changed,
        reference_observed=_seen_by_any(scan_origins, reference_exact, *worlds["scan"]),
        scan_observed=_seen_by_any(reference_origins, scan_exact, *worlds["reference"]),
    )
