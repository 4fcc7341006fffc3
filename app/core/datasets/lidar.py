"""Random ray-cast lidar rescans of rooms, corridors and warehouses, with exact ground truth.

The class of issue 15: a closed shell 8-30 m long with boxes and racks (solid axis-aligned
boxes), scanned by a spinning lidar on a regular angular grid (elevation -45 to 60 degrees) from
one or several stations 0.8-1.5 m above the floor; the second epoch moves every station
0.1-1.5 m and may add, remove or move boxes.  Files are in the world frame, which is offset from
the building so that no sensor sits at the file's origin; the scan may be misaligned by a small
rigid transform.  Stations of one epoch are concatenated, then shuffled.

Truth (as in the issue): a point is changed when its exact (noise-free) position lies more than
:data:`CHANGE_DISTANCE` from every surface of the other epoch's world; it is observed when at
least one station of the other epoch could see it (in range, in the field of view and not hidden
behind the other world).  Ray casting reuses :func:`app.core.datasets.scenes._cast_rays`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from app.core.datasets.scenes import _cast_rays, _random_rotation, _transform_points, _visible_from

__all__ = [
    "CHANGE_DISTANCE",
    "LAYOUTS",
    "LIDAR_CHANGES",
    "DrawnScene",
    "LidarPair",
    "LidarWorld",
    "draw_scene",
    "file_frame",
    "lidar_directions",
    "lidar_pair",
    "steps_for_points",
]

LAYOUTS = ("room", "corridor", "warehouse")
"""Values accepted by ``lidar_pair(layout=...)``."""
LIDAR_CHANGES = ("none", "added", "removed", "moved", "mixed")
"""Values accepted by ``lidar_pair(change=...)``; ``"mixed"`` does all three."""
CHANGE_DISTANCE = 0.10
"""A point farther than this (metres) from every surface of the other world is changed."""
ELEVATION_RANGE_DEG = (-45.0, 60.0)
"""Vertical field of view of the lidar, degrees above the sensor's horizontal plane."""
RANGE_LIMITS = (0.3, 120.0)
"""Minimum and maximum range of the lidar (metres)."""
SENSOR_HEIGHT_RANGE = (0.8, 1.5)
SENSOR_SHIFT_RANGE = (0.1, 1.5)
MISALIGNMENT = ((0.02, 0.03), (0.3, 0.4))
"""(translation metres, rotation degrees) ranges of the optional misalignment of the scan."""
MIN_VISIBLE_CHANGE = 100
"""A changed pair on a 0.6 degree grid has at least this many changed, observed points."""
CLEARANCE = 0.5
"""Sensors stay at least this far (metres) from every wall and box."""
CAST_CHUNK = 1 << 19
"""Rays or points per step of :class:`LidarWorld`'s ray casts and distances: the results do not
depend on it; it bounds their temporaries (a 20M-point epoch otherwise holds several (p, 3)
float64 arrays per box at once) and keeps them in cache."""


@dataclass(frozen=True)
class LidarWorld:
    """A closed shell with solid boxes in it, world coordinates (metres).

    Attributes
    ----------
    shell_low, shell_high : ndarray, shape (3,)
        Inner corners of the shell (floor at ``shell_low[2]``).
    box_low, box_high : ndarray, shape (b, 3)
        Corners of the solid boxes and racks.
    """

    shell_low: NDArray[np.float64]
    shell_high: NDArray[np.float64]
    box_low: NDArray[np.float64]
    box_high: NDArray[np.float64]

    def surface_distance(self, points: NDArray[np.float64]) -> NDArray[np.float64]:
        """Distance from each point to the nearest surface (shell face or box face), shape (p,)."""
        return _chunked(self._surface_distance, points)

    def _surface_distance(self, points: NDArray[np.float64]) -> NDArray[np.float64]:
        inside_shell = np.minimum(points - self.shell_low, self.shell_high - points)
        distance = np.abs(inside_shell).min(axis=1)
        for low, high in zip(self.box_low, self.box_high, strict=True):
            gap = np.maximum(np.maximum(low - points, points - high), 0.0)
            outside = np.linalg.norm(gap, axis=1)
            depth = np.minimum(points - low, high - points).min(axis=1)
            distance = np.minimum(distance, np.where(outside > 0.0, outside, np.abs(depth)))
        return distance

    def cast(
        self, origin: NDArray[np.float64], directions: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """First hit along unit ``directions`` (r, 3) from ``origin``: (distance, box or -1)."""
        parts = [
            _cast_rays(
                origin,
                directions[start : start + CAST_CHUNK],
                self.box_low,
                self.box_high,
                shell_low=self.shell_low,
                shell_high=self.shell_high,
            )
            for start in range(0, max(1, len(directions)), CAST_CHUNK)
        ]
        return np.concatenate([part[0] for part in parts]), np.concatenate(
            [part[1] for part in parts]
        )

    def visible_from(
        self, origin: NDArray[np.float64], points: NDArray[np.float64]
    ) -> NDArray[np.bool_]:
        """Whether an upright lidar at ``origin`` sees the exact surface ``points`` (p, 3)."""
        return _chunked(lambda chunk: self._visible_from(origin, chunk), points)

    def _visible_from(
        self, origin: NDArray[np.float64], points: NDArray[np.float64]
    ) -> NDArray[np.bool_]:
        return _visible_from(
            origin,
            points,
            self.box_low,
            self.box_high,
            range_limits=RANGE_LIMITS,
            elevation_deg=ELEVATION_RANGE_DEG,
            shell_low=self.shell_low,
            shell_high=self.shell_high,
        )


def _chunked(function: Callable[[NDArray], NDArray], points: NDArray) -> NDArray:
    """``function`` of ``points`` (p, 3), a row-wise map, :data:`CAST_CHUNK` rows at a time."""
    if len(points) <= CAST_CHUNK:
        return function(points)
    return np.concatenate(
        [
            function(points[start : start + CAST_CHUNK])
            for start in range(0, len(points), CAST_CHUNK)
        ]
    )


@dataclass(frozen=True)
class LidarPair:
    """Two epochs of one place, in file coordinates, with the truth.

    Attributes
    ----------
    reference, scan : ndarray, shape (n, 3) and (m, 3)
        Points in each file's frame (the reference's is the world frame; the scan's differs by
        the misalignment, if any).
    reference_changed, scan_changed : ndarray, shape (n,) and (m,), bool
        More than :data:`CHANGE_DISTANCE` from every surface of the other epoch's world.
    reference_observed, scan_observed : ndarray, bool
        Seen by at least one station of the other epoch (unobserved points are not scored).
    reference_station, scan_station : ndarray, int64
        Index of the station (row of the origins) each point was taken from.
    reference_origins, scan_origins : ndarray, shape (s, 3)
        True station positions, in each file's frame.
    true_transform : ndarray, shape (4, 4)
        Maps scan-file coordinates into the reference frame.
    layout, change : str
    elevation_step_deg, azimuth_step_deg : float
        The lidar's angular grid.
    """

    reference: NDArray[np.float64]
    scan: NDArray[np.float64]
    reference_changed: NDArray[np.bool_]
    scan_changed: NDArray[np.bool_]
    reference_observed: NDArray[np.bool_]
    scan_observed: NDArray[np.bool_]
    reference_station: NDArray[np.int64]
    scan_station: NDArray[np.int64]
    reference_origins: NDArray[np.float64]
    scan_origins: NDArray[np.float64]
    true_transform: NDArray[np.float64]
    layout: str
    change: str
    elevation_step_deg: float
    azimuth_step_deg: float

    @property
    def reference_origin(self) -> NDArray[np.float64]:
        """The first reference station, shape (3,) (the only one for single-station pairs)."""
        return self.reference_origins[0]

    @property
    def scan_origin(self) -> NDArray[np.float64]:
        """The first scan station in the scan's frame, shape (3,)."""
        return self.scan_origins[0]


def steps_for_points(points_per_scan: int, n_stations: int = 1) -> float:
    """The angular step (degrees, both axes) giving about ``points_per_scan`` rays a scan.

    Closed shells return every ray, so this is about the point count too.
    """
    span = ELEVATION_RANGE_DEG[1] - ELEVATION_RANGE_DEG[0]
    rays_per_station = points_per_scan / max(n_stations, 1)
    return float(np.sqrt(span * 360.0 / rays_per_station))


def lidar_directions(
    elevation_step_deg: float, azimuth_step_deg: float, yaw_deg: float = 0.0
) -> NDArray[np.float64]:
    """Unit ray directions of one upright spinning-lidar sweep on a regular grid, shape (r, 3).

    Rings at ``-45, -45 + step, ... <= 60`` degrees elevation; columns every
    ``azimuth_step_deg`` degrees from ``yaw_deg``.
    """
    low, high = ELEVATION_RANGE_DEG
    elevation = np.deg2rad(np.arange(low, high + 1e-9, elevation_step_deg))
    azimuth = np.deg2rad(yaw_deg + np.arange(0.0, 360.0 - 1e-9, azimuth_step_deg))
    elevation_grid, azimuth_grid = np.meshgrid(elevation, azimuth, indexing="ij")
    cos_elevation = np.cos(elevation_grid.ravel())
    return np.column_stack(
        [
            cos_elevation * np.cos(azimuth_grid.ravel()),
            cos_elevation * np.sin(azimuth_grid.ravel()),
            np.sin(elevation_grid.ravel()),
        ]
    )


def _random_box(
    rng: np.random.Generator, low: NDArray, high: NDArray, size_range: tuple, height_range: tuple
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    size = rng.uniform(*size_range, 2)
    height = rng.uniform(*height_range)
    corner = rng.uniform(low[:2], high[:2] - size)
    return np.array([*corner, low[2]]), np.array([*(corner + size), low[2] + height])


def _overlaps(low: NDArray, high: NDArray, lows: list, highs: list, margin: float) -> bool:
    return any(
        np.all(low < other_high + margin) and np.all(high > other_low - margin)
        for other_low, other_high in zip(lows, highs, strict=True)
    )


def _layout(layout: str, rng: np.random.Generator) -> tuple[NDArray, NDArray, list, list, int]:
    """Shell corners, box corners and how many leading boxes are racks (never changed)."""
    if layout == "room":
        extent = [rng.uniform(8.0, 16.0), rng.uniform(6.0, 12.0), rng.uniform(2.6, 3.5)]
        racks, boxes, box_size, box_height = 0, rng.integers(4, 11), (0.4, 1.5), (0.4, 1.8)
    elif layout == "corridor":
        extent = [rng.uniform(12.0, 30.0), rng.uniform(2.2, 3.5), rng.uniform(2.5, 3.2)]
        racks, boxes, box_size, box_height = 0, rng.integers(2, 7), (0.3, 0.7), (0.4, 1.4)
    elif layout == "warehouse":
        extent = [rng.uniform(15.0, 30.0), rng.uniform(10.0, 25.0), rng.uniform(5.0, 8.0)]
        racks, boxes = rng.integers(2, 7), rng.integers(3, 11)
        box_size, box_height = (0.5, 1.5), (0.4, 1.8)
    else:
        raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
    shell_low = np.array([0.0, 0.0, 0.0])
    shell_high = np.array(extent)
    lows: list[NDArray] = []
    highs: list[NDArray] = []
    for _ in range(int(racks)):  # long, tall, parallel to x
        for _attempt in range(50):
            length, depth, height = (
                rng.uniform(4.0, 12.0),
                rng.uniform(0.8, 1.2),
                rng.uniform(2, 4.5),
            )
            length = min(length, extent[0] - 4.0)
            corner = rng.uniform([2.0, 1.0], [extent[0] - 2.0 - length, extent[1] - 1.0 - depth])
            low = np.array([*corner, 0.0])
            high = np.array([corner[0] + length, corner[1] + depth, min(height, extent[2] - 0.5)])
            if not _overlaps(low, high, lows, highs, 2.5):
                lows.append(low)
                highs.append(high)
                break
    n_racks = len(lows)
    for _ in range(int(boxes)):
        for _attempt in range(50):
            low, high = _random_box(rng, shell_low, shell_high, box_size, box_height)
            if not _overlaps(low, high, lows, highs, 0.3):
                lows.append(low)
                highs.append(high)
                break
    return shell_low, shell_high, lows, highs, n_racks


def _free_position(
    rng: np.random.Generator, world: LidarWorld, near: NDArray | None, shift: tuple
) -> NDArray[np.float64]:
    """A sensor position clear of walls and boxes: anywhere, or ``shift`` metres from ``near``."""
    for _ in range(2000):
        height = world.shell_low[2] + rng.uniform(*SENSOR_HEIGHT_RANGE)
        if near is None:
            xy = rng.uniform(world.shell_low[:2] + CLEARANCE, world.shell_high[:2] - CLEARANCE)
        else:
            heading = rng.uniform(0.0, 2.0 * np.pi)
            xy = near[:2] + rng.uniform(*shift) * np.array([np.cos(heading), np.sin(heading)])
        candidate = np.array([*xy, height])
        inside = np.all(candidate[:2] > world.shell_low[:2] + CLEARANCE) and np.all(
            candidate[:2] < world.shell_high[:2] - CLEARANCE
        )
        gap = np.maximum(np.maximum(world.box_low - candidate, candidate - world.box_high), 0.0)
        if inside and (len(gap) == 0 or np.linalg.norm(gap, axis=1).min() >= CLEARANCE):
            return candidate
    raise ValueError("no free sensor position in this layout; try another seed")


def _changed_boxes(
    change: str, rng: np.random.Generator, lows: list, highs: list, n_racks: int, shell: tuple
) -> tuple[list, list, list, list]:
    """(reference lows, highs), (scan lows, highs) after ``change``."""
    if change not in LIDAR_CHANGES:
        raise ValueError(f"change must be one of {LIDAR_CHANGES}, got {change!r}")
    reference_lows, reference_highs = list(lows), list(highs)
    scan_lows, scan_highs = list(lows), list(highs)
    movable = list(range(n_racks, len(lows)))
    rng.shuffle(movable)

    def place(size: NDArray | None) -> tuple[NDArray, NDArray] | None:
        for _ in range(200):
            if size is None:
                low, high = _random_box(rng, *shell, (0.5, 1.2), (0.5, 1.2))
            else:
                corner = rng.uniform(shell[0][:2], shell[1][:2] - size[:2])
                low = np.array([*corner, shell[0][2]])
                high = low + size
            all_lows, all_highs = reference_lows + scan_lows, reference_highs + scan_highs
            if not _overlaps(low, high, all_lows, all_highs, 0.4):
                return low, high
        return None

    if change in ("removed", "mixed") and movable:
        index = movable.pop()
        scan_lows[index] = np.full(3, np.nan)  # keeps the indices; dropped below
        scan_highs[index] = np.full(3, np.nan)
    if change in ("moved", "mixed") and movable:
        index = movable.pop()
        placed = place(highs[index] - lows[index])
        if placed is not None:
            scan_lows[index], scan_highs[index] = placed
    if change in ("added", "mixed"):
        placed = place(None)
        if placed is not None:
            scan_lows.append(placed[0])
            scan_highs.append(placed[1])
    keep = [i for i, low in enumerate(scan_lows) if np.isfinite(low).all()]
    return (
        reference_lows,
        reference_highs,
        [scan_lows[i] for i in keep],
        [scan_highs[i] for i in keep],
    )


def _world(shell_low: NDArray, shell_high: NDArray, lows: list, highs: list) -> LidarWorld:
    return LidarWorld(
        shell_low=shell_low,
        shell_high=shell_high,
        box_low=np.array(lows, dtype=np.float64).reshape(-1, 3),
        box_high=np.array(highs, dtype=np.float64).reshape(-1, 3),
    )


def _scan_epoch(
    world: LidarWorld,
    stations: NDArray,
    steps: tuple[float, float],
    range_noise: float,
    rng: np.random.Generator,
) -> tuple[NDArray, NDArray, NDArray]:
    """(noisy points, exact points, station index) of all stations, concatenated."""
    noisy, exact, station_index = [], [], []
    for index, station in enumerate(stations):
        directions = lidar_directions(*steps, yaw_deg=rng.uniform(0.0, 360.0))
        distance, _ = world.cast(station, directions)
        keep = (distance >= RANGE_LIMITS[0]) & (distance <= RANGE_LIMITS[1])
        directions, distance = directions[keep], distance[keep]
        exact.append(station + distance[:, None] * directions)
        measured = distance + rng.normal(0.0, range_noise, distance.shape)
        noisy.append(station + measured[:, None] * directions)
        station_index.append(np.full(distance.size, index, dtype=np.int64))
    return np.vstack(noisy), np.vstack(exact), np.concatenate(station_index)


def _observed_by(world: LidarWorld, stations: NDArray, points: NDArray) -> NDArray[np.bool_]:
    observed = np.zeros(len(points), dtype=bool)
    for station in stations:
        observed |= world.visible_from(station, points)
    return observed


def lidar_pair(
    *,
    layout: str = "room",
    change: str = "added",
    n_stations: int = 1,
    angular_step_deg: float | tuple[float, float] = 0.6,
    range_noise: float = 0.01,
    misaligned: bool = False,
    random_state: int | np.random.Generator | None = None,
) -> LidarPair:
    """A random two-epoch lidar rescan of one layout, with exact truth.

    Parameters
    ----------
    layout : {"room", "corridor", "warehouse"}
        Room 8-16 x 6-12 x 2.6-3.5 m with 4-10 boxes; corridor 12-30 x 2.2-3.5 m with 2-6
        boxes; warehouse 15-30 x 10-25 x 5-8 m with 2-6 racks (never changed) and 3-10 boxes.
        Sizes, counts and positions are drawn from ``random_state``.
    change : {"none", "added", "removed", "moved", "mixed"}
        In the scan's world: a new 0.5-1.2 m box; one box gone; one box moved elsewhere;
        all three.
    n_stations : int
        Stations per epoch (1 for a single-station scan; 3-5 for a merged survey).  Reference
        stations are anywhere free; each scan station is 0.1-1.5 m from its reference station.
    angular_step_deg : float or (float, float)
        (elevation, azimuth) step of the lidar grid; :func:`steps_for_points` gives the step for
        a point budget (0.2 degrees and one station: about 1M points).
    range_noise : float
        Standard deviation (metres) of the Gaussian range noise.
    misaligned : bool
        Rotate the scan file by 0.3-0.4 degrees about a random axis through the building's
        centre and shift it 2-3 cm (``true_transform`` undoes it).
    random_state : int, Generator or None

    Returns
    -------
    LidarPair
        Points of each epoch's stations concatenated, then shuffled.  A changed pair has at
        least :data:`MIN_VISIBLE_CHANGE` (at a 0.6 degree grid; scaled with the density, at least
        10) changed points seen by the other epoch (layouts are redrawn until it does).
    """
    if n_stations < 1:
        raise ValueError(f"n_stations must be at least 1, got {n_stations}")
    steps = np.broadcast_to(np.asarray(angular_step_deg, dtype=np.float64), (2,))
    if not np.all((steps > 0.0) & (steps <= 10.0)):
        raise ValueError(f"angular_step_deg must be in (0, 10], got {angular_step_deg}")
    rng = np.random.default_rng(random_state)
    # the floor on visible changed points scales with the density (0.6 degrees: the constant)
    needed = max(10.0, MIN_VISIBLE_CHANGE * 0.36 / float(steps[0] * steps[1]))
    for _ in range(20):
        pair = _draw_pair(layout, change, n_stations, steps, range_noise, misaligned, rng)
        visible_change = np.count_nonzero(pair.reference_changed & pair.reference_observed)
        visible_change += np.count_nonzero(pair.scan_changed & pair.scan_observed)
        if change == "none" or visible_change >= needed:
            return pair
    raise ValueError(f"no visible {change!r} change in 20 layouts; try another seed")


@dataclass(frozen=True)
class DrawnScene:
    """The building, the two epochs' worlds and stations of one draw (before any ray is cast).

    Attributes
    ----------
    shell_low, shell_high : ndarray, shape (3,)
        The building's shell.
    reference_world, scan_world : LidarWorld
        Each epoch's boxes in the shell.
    reference_stations, scan_stations : ndarray, shape (s, 3)
        Each epoch's stations (a scan station near its reference station).
    """

    shell_low: NDArray[np.float64]
    shell_high: NDArray[np.float64]
    reference_world: LidarWorld
    scan_world: LidarWorld
    reference_stations: NDArray[np.float64]
    scan_stations: NDArray[np.float64]


def draw_scene(layout: str, change: str, n_stations: int, rng: np.random.Generator) -> DrawnScene:
    """The first draws of :func:`lidar_pair`: layout, changed boxes, worlds and stations (the
    bounded-memory writer, :mod:`app.core.datasets.lidar_files`, makes the same draws)."""
    shell_low, shell_high, lows, highs, n_racks = _layout(layout, rng)
    reference_lows, reference_highs, scan_lows, scan_highs = _changed_boxes(
        change, rng, lows, highs, n_racks, (shell_low, shell_high)
    )
    both = _world(shell_low, shell_high, reference_lows + scan_lows, reference_highs + scan_highs)
    reference_stations = np.array([_free_position(rng, both, None, ()) for _ in range(n_stations)])
    scan_stations = np.array(
        [_free_position(rng, both, station, SENSOR_SHIFT_RANGE) for station in reference_stations]
    )
    return DrawnScene(
        shell_low=shell_low,
        shell_high=shell_high,
        reference_world=_world(shell_low, shell_high, reference_lows, reference_highs),
        scan_world=_world(shell_low, shell_high, scan_lows, scan_highs),
        reference_stations=reference_stations,
        scan_stations=scan_stations,
    )


def file_frame(
    rng: np.random.Generator,
    shell_low: NDArray[np.float64],
    shell_high: NDArray[np.float64],
    misaligned: bool,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The last draws of :func:`lidar_pair` before its shuffle: the file frame's offset, shape
    (3,) (the building away from the file's origin), and the scan file's pose, shape (4, 4)
    (scan file = pose @ world)."""
    offset = np.array([*rng.uniform(-60.0, 60.0, 2), rng.uniform(-3.0, 3.0)])
    offset[:2] += np.sign(offset[:2]) * 5.0
    pose = np.eye(4)
    if misaligned:
        (t_low, t_high), (r_low, r_high) = MISALIGNMENT
        rotation = _random_rotation(rng.uniform(r_low, r_high), rng)
        direction = rng.normal(size=3)
        translation = rng.uniform(t_low, t_high) * direction / np.linalg.norm(direction)
        centre = (shell_low + shell_high) / 2.0 + offset
        pose[:3, :3] = rotation
        pose[:3, 3] = centre - rotation @ centre + translation
    return offset, pose


def _draw_pair(
    layout: str,
    change: str,
    n_stations: int,
    steps: NDArray[np.float64],
    range_noise: float,
    misaligned: bool,
    rng: np.random.Generator,
) -> LidarPair:
    """One draw of :func:`lidar_pair` (which redraws when the change was not seen)."""
    scene = draw_scene(layout, change, n_stations, rng)
    shell_low, shell_high = scene.shell_low, scene.shell_high
    reference_world, scan_world = scene.reference_world, scene.scan_world
    reference_stations, scan_stations = scene.reference_stations, scene.scan_stations
    step_pair = (float(steps[0]), float(steps[1]))
    reference, reference_exact, reference_station = _scan_epoch(
        reference_world, reference_stations, step_pair, range_noise, rng
    )
    scan, scan_exact, scan_station = _scan_epoch(
        scan_world, scan_stations, step_pair, range_noise, rng
    )
    reference_changed = scan_world.surface_distance(reference_exact) > CHANGE_DISTANCE
    scan_changed = reference_world.surface_distance(scan_exact) > CHANGE_DISTANCE
    reference_observed = _observed_by(scan_world, scan_stations, reference_exact)
    scan_observed = _observed_by(reference_world, reference_stations, scan_exact)

    offset, pose = file_frame(rng, shell_low, shell_high, misaligned)
    reference_order = rng.permutation(len(reference))
    scan_order = rng.permutation(len(scan))
    return LidarPair(
        reference=(reference + offset)[reference_order],
        scan=_transform_points(scan + offset, pose)[scan_order],
        reference_changed=reference_changed[reference_order],
        scan_changed=scan_changed[scan_order],
        reference_observed=reference_observed[reference_order],
        scan_observed=scan_observed[scan_order],
        reference_station=reference_station[reference_order],
        scan_station=scan_station[scan_order],
        reference_origins=reference_stations + offset,
        scan_origins=_transform_points(scan_stations + offset, pose),
        true_transform=np.linalg.inv(pose),
        layout=layout,
        change=change,
        elevation_step_deg=step_pair[0],
        azimuth_step_deg=step_pair[1],
    )


def random_world(layout: str, rng: np.random.Generator) -> LidarWorld:
    """A random building of ``layout`` ("room", "corridor", ...), drawn as :func:`lidar_pair`
    draws its buildings (the same draws from ``rng``)."""
    shell_low, shell_high, lows, highs, _ = _layout(layout, rng)
    return _world(shell_low, shell_high, lows, highs)


def free_sensor_position(rng: np.random.Generator, world: LidarWorld) -> NDArray[np.float64]:
    """A sensor position in ``world`` clear of its walls and boxes, shape (3,)."""
    return _free_position(rng, world, None, ())
