"""A synthetic site's history: rescans of one room where a bin moves every time (a nuisance)
and, now and then, a real change (a new crate) appears.

Built on the ray-cast building of :func:`app.core.datasets.scenes.raycast_scene` (room A, its
furniture, the spinning lidar): every visit casts a sweep from a sensor standing near the
reference sensor (``sensor_shift`` metres away, a random free direction) in a world made of
the static furniture, the bin at one of a few spots along the walls, and, on a real-change
visit, a 1 x 1 x 1 m crate.  Scans are in the world frame (no pose error), with their sensor
origin, so a comparison's only differences are the bin, the crate and sampling.

Used by the calibration test (a site that learns to ignore the bin) and
``bench/calibration.py`` (false alarms before/after learning, detection of the crate).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from app.core.datasets.scenes import (
    REFERENCE_SENSOR_XY,
    SENSOR_HEIGHT,
    STATIC_BOXES,
    SceneBox,
    _box_arrays,
    _cast_rays,
    _lidar_directions,
    _place_scan_sensor,
)

BIN_SIZE = (0.4, 0.4, 0.7)
"""The nuisance: a wheelie bin (metres), smaller than the real change."""
CRATE_SIZE = (1.0, 1.0, 1.0)
"""The real change: a crate left in the room (metres)."""
BIN_SPOTS: tuple[tuple[float, float], ...] = (
    (1.2, 0.15),
    (3.2, 0.15),
    (8.6, 0.15),
    (9.4, 1.6),
    (1.0, 4.6),
    (9.4, 4.8),
    (8.4, 7.4),
    (1.4, 7.4),
)
"""Where the bin may stand (x, y of its low corner), along the walls of room A, clear of the
furniture and at least 2.5 m from the reference sensor (closer, the lidar sees only its top)."""
CRATE_SPOTS: tuple[tuple[float, float], ...] = ((5.4, 1.0), (2.0, 3.6), (7.8, 4.2), (3.0, 5.4))
"""Where the crate may appear (x, y of its low corner), in the open floor of room A."""


@dataclass(frozen=True)
class SiteVisit:
    """One scan of the site: its points (world frame) and what changed since the reference."""

    points: NDArray[np.float64]
    sensor_origin: NDArray[np.float64]
    bin_spot: int
    crate_spot: int | None

    @property
    def real_change(self) -> bool:
        """Whether the crate is there (a change a reviewer wants to hear about)."""
        return self.crate_spot is not None


def _box_at(name: str, spot: tuple[float, float], size: tuple[float, float, float]) -> SceneBox:
    return SceneBox(name, (spot[0], spot[1], 0.0), (spot[0] + size[0], spot[1] + size[1], size[2]))


def site_visit(
    *,
    bin_spot: int,
    crate_spot: int | None = None,
    crate_size: float = CRATE_SIZE[0],
    n_points: int = 20_000,
    sensor_shift: float = 0.5,
    range_noise: float = 0.01,
    random_state: int | np.random.Generator | None = None,
) -> SiteVisit:
    """One lidar sweep of room A with the bin at ``BIN_SPOTS[bin_spot]`` (and the crate).

    Parameters
    ----------
    bin_spot : int
        Index into :data:`BIN_SPOTS`.
    crate_spot : int, optional
        Index into :data:`CRATE_SPOTS`; None: no crate.
    crate_size : float
        Edge of the (cubic) crate, metres; default :data:`CRATE_SIZE`.
    n_points : int
        Rays (points) of the sweep, >= 1000.
    sensor_shift : float
        Horizontal distance (metres) of the sensor from the reference sensor; 0 puts it there.
    range_noise : float
        Standard deviation (metres) of the range noise.
    random_state : int, Generator or None

    Returns
    -------
    SiteVisit
        ``points`` has shape (n_points, 3), ``sensor_origin`` shape (3,).
    """
    if n_points < 1000:
        raise ValueError(f"n_points must be at least 1000, got {n_points}")
    rng = np.random.default_rng(random_state)
    world = [*STATIC_BOXES, _box_at("bin", BIN_SPOTS[bin_spot], BIN_SIZE)]
    if crate_spot is not None:
        world.append(_box_at("crate", CRATE_SPOTS[crate_spot], (crate_size,) * 3))
    if sensor_shift > 0:
        sensor = _place_scan_sensor(sensor_shift, world, rng)
    else:
        sensor = np.array([*REFERENCE_SENSOR_XY, SENSOR_HEIGHT])
    low, high = _box_arrays(world)
    directions = _lidar_directions(n_points, rng)
    distance, _ = _cast_rays(sensor, directions, low, high)
    distance = distance + rng.normal(0.0, range_noise, distance.shape)
    points = sensor + distance[:, None] * directions
    return SiteVisit(points, sensor, bin_spot, crate_spot)


def site_history(
    n_visits: int,
    *,
    layout_seed: int,
    real_change_visits: tuple[int, ...] = (),
    crate_size: float = CRATE_SIZE[0],
    n_points: int = 20_000,
) -> tuple[SiteVisit, list[SiteVisit]]:
    """A reference and ``n_visits`` rescans of one layout; the bin moves on every visit.

    The layout (``layout_seed``) fixes the bin's spots (the reference's, then a different one
    on each visit, drawn from :data:`BIN_SPOTS`) and the crate's spot; visits whose index is in
    ``real_change_visits`` also have the crate (edge ``crate_size`` metres).  Sensor positions
    (0.3-0.8 m from the reference sensor) and sampling vary per visit.

    Returns
    -------
    reference : SiteVisit
    visits : list of SiteVisit
    """
    rng = np.random.default_rng(layout_seed)
    reference_spot = int(rng.integers(len(BIN_SPOTS)))
    crate_spot = int(rng.integers(len(CRATE_SPOTS)))
    reference = site_visit(
        bin_spot=reference_spot, n_points=n_points, sensor_shift=0.0, random_state=rng
    )
    others = [spot for spot in range(len(BIN_SPOTS)) if spot != reference_spot]
    visits = [
        site_visit(
            bin_spot=int(rng.choice(others)),
            crate_spot=crate_spot if index in real_change_visits else None,
            crate_size=crate_size,
            n_points=n_points,
            sensor_shift=float(rng.uniform(0.3, 0.8)),
            random_state=rng,
        )
        for index in range(n_visits)
    ]
    return reference, visits
