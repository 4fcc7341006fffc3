"""Synthetic scan pairs with exact ground truth, for tests, benchmarks and the demo.

Two generators:

:func:`paper_corridor`
    The corridor of the paper's section IV: two parallel walls and a ceiling sampled with a few
    hundred points, Gaussian noise, and a "box pushed out of a wall" made by moving some of one
    wall's points into the corridor.
:func:`raycast_scene`
    A ray-cast spinning-lidar scan of two furnished rooms joined by a doorway, taken twice from
    sensor positions about a metre apart, with range noise, occlusions, density falling with
    range, a pose error on the second scan, and an object added, removed or moved. Ray casting
    is exact (ray/box slab tests, vectorised over rays), so the ground-truth "observed" masks
    are exact too.

Both return a :class:`SyntheticPair`.  Conventions shared by both:

* ``reference_changed`` marks reference points on surfaces that no longer exist in the scan's
  world ("removed"); ``scan_changed`` marks scan points on surfaces that did not exist in the
  reference's world ("added").
* ``reference_observed`` says whether the *scan's* sensor could have seen the reference point
  (in range, inside its field of view and not hidden behind the scan-time world);
  ``scan_observed`` likewise for scan points w.r.t. the reference sensor and world.  A point
  that is not observed should be labelled unobserved by a localiser, never changed.
* ``scan`` and ``scan_origin`` are in the scan's own frame; ``true_transform`` maps that frame
  into the reference frame (``reference_frame = R @ scan_frame + t``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "CHANGE_KINDS",
    "CORRIDOR_BOX_DEPTH",
    "STATIC_BOXES",
    "SceneBox",
    "SyntheticPair",
    "paper_corridor",
    "raycast_scene",
    "raycast_scene_objects",
]

CORRIDOR_HALF_WIDTH = 1.0
"""The corridor's walls are the planes x = -1 and x = +1 (metres)."""
CORRIDOR_LENGTH = 4.0
"""The corridor runs along y from -2 to +2."""
CORRIDOR_HEIGHT = 2.0
"""Walls span z from 0 to 2; the ceiling is the plane z = 2 (there is no floor, as in the paper)."""
CORRIDOR_BOX_DEPTH = 0.5
"""How far (metres) the changed wall patch is pushed into the corridor to form the box."""

CHANGE_KINDS = ("none", "box", "removed", "moved", "mixed")
"""Values accepted by ``raycast_scene(change=...)``."""


@dataclass(frozen=True)
class SyntheticPair:
    """A reference scan, a later scan of the same place, and the exact ground truth.

    Attributes
    ----------
    reference : ndarray, shape (n, 3), float64
        Reference points, in the reference frame.
    scan : ndarray, shape (m, 3), float64
        Scan points in the scan's own frame (the pose error is applied).
    reference_changed : ndarray, shape (n,), bool
        Reference points on surfaces that are gone in the scan's world ("removed").
    scan_changed : ndarray, shape (m,), bool
        Scan points on surfaces that are new ("added").
    reference_observed : ndarray, shape (n,), bool
        The scan's sensor could see where the reference point lies (in range, in view, not
        occluded by the scan-time world).  False means it should be labelled unobserved.
    scan_observed : ndarray, shape (m,), bool
        Likewise for scan points w.r.t. the reference sensor and world.
    reference_origin : ndarray, shape (3,)
        Reference sensor position, reference frame.
    scan_origin : ndarray, shape (3,)
        Scan sensor position, in the scan's own frame.
    true_transform : ndarray, shape (4, 4)
        Homogeneous transform mapping scan-frame coordinates into the reference frame (the
        inverse of the pose error).
    """

    reference: NDArray[np.float64]
    scan: NDArray[np.float64]
    reference_changed: NDArray[np.bool_]
    scan_changed: NDArray[np.bool_]
    reference_observed: NDArray[np.bool_]
    scan_observed: NDArray[np.bool_]
    reference_origin: NDArray[np.float64]
    scan_origin: NDArray[np.float64]
    true_transform: NDArray[np.float64]

    def aligned_scan(self) -> NDArray[np.float64]:
        """The scan mapped into the reference frame with ``true_transform``, shape (m, 3)."""
        return _transform_points(self.scan, self.true_transform)

    def aligned_scan_origin(self) -> NDArray[np.float64]:
        """The scan sensor position in the reference frame, shape (3,)."""
        return _transform_points(self.scan_origin[None, :], self.true_transform)[0]


def _transform_points(points: NDArray[np.float64], transform: NDArray[np.float64]) -> NDArray:
    return points @ transform[:3, :3].T + transform[:3, 3]


# --------------------------------------------------------------------------------------------
# The paper's corridor
# --------------------------------------------------------------------------------------------


def paper_corridor(
    n_points: int = 300,
    noise_variance: float = 1e-3,
    change_fraction: float = 0.0,
    random_state: int | np.random.Generator | None = None,
) -> SyntheticPair:
    """The paper's corridor (section IV) with a box pushed out of one wall.

    ``n_points`` noise-free points are drawn uniformly on three surfaces of equal area (4 m x
    2 m each): the walls x = -1 and x = +1 and the ceiling z = 2 (y in [-2, 2], z in [0, 2]).
    The reference and the scan are these same points with independent Gaussian noise of
    variance ``noise_variance`` on every coordinate.  In the scan, the
    ``round(change_fraction * n_points)`` points of the wall x = -1 nearest (in the Chebyshev
    sense, giving a square patch) to the wall's centre (y = 0, z = 1) are pushed
    :data:`CORRIDOR_BOX_DEPTH` (0.5 m) into the corridor, to x = -0.5: the front of a box
    standing out of the wall.

    Ground truth: the pushed points are ``scan_changed`` ("added": the box's front face); the
    same points' original wall positions in the reference are ``reference_changed`` ("removed":
    the wall patch the box now covers, which has no points in the scan).  Point ``i`` of the
    reference and of the scan come from the same noise-free point, so both masks are equal.
    Every point is observed (the corridor is not a ray-consistent scan, so compare it without
    sensor origins).  Origins are the corridor's centre (0, 0, 1); the transform is identity.

    Parameters
    ----------
    n_points : int
        Points per cloud (>= 12).
    noise_variance : float
        Variance (m^2) of the zero-mean Gaussian noise on each coordinate; the paper uses
        1e-5 ... 1e-1.
    change_fraction : float
        Fraction of all points moved into the box, in [0, 1/3] (the box comes out of one wall,
        which holds a third of the points); the paper uses 0.03 ... 0.33.
    random_state : int, Generator or None

    Returns
    -------
    SyntheticPair
        ``n == m == n_points``.
    """
    if n_points < 12:
        raise ValueError(f"n_points must be at least 12, got {n_points}")
    if noise_variance < 0:
        raise ValueError(f"noise_variance must be >= 0, got {noise_variance}")
    rng = np.random.default_rng(random_state)
    per_surface = np.full(3, n_points // 3)
    per_surface[: n_points % 3] += 1
    n_changed = round(change_fraction * n_points)
    if not 0.0 <= change_fraction or n_changed > per_surface[0]:
        raise ValueError(
            f"change_fraction must be in [0, {per_surface[0] / n_points:.3f}] (the box comes "
            f"out of one wall holding {per_surface[0]} of {n_points} points), got {change_fraction}"
        )
    half_length = CORRIDOR_LENGTH / 2.0
    left_wall = np.column_stack(
        [
            np.full(per_surface[0], -CORRIDOR_HALF_WIDTH),
            rng.uniform(-half_length, half_length, per_surface[0]),
            rng.uniform(0.0, CORRIDOR_HEIGHT, per_surface[0]),
        ]
    )
    right_wall = np.column_stack(
        [
            np.full(per_surface[1], CORRIDOR_HALF_WIDTH),
            rng.uniform(-half_length, half_length, per_surface[1]),
            rng.uniform(0.0, CORRIDOR_HEIGHT, per_surface[1]),
        ]
    )
    ceiling = np.column_stack(
        [
            rng.uniform(-CORRIDOR_HALF_WIDTH, CORRIDOR_HALF_WIDTH, per_surface[2]),
            rng.uniform(-half_length, half_length, per_surface[2]),
            np.full(per_surface[2], CORRIDOR_HEIGHT),
        ]
    )
    clean = np.vstack([left_wall, right_wall, ceiling])
    changed = np.zeros(n_points, dtype=bool)
    if n_changed > 0:
        chebyshev = np.maximum(np.abs(left_wall[:, 1]), np.abs(left_wall[:, 2] - 1.0))
        changed[np.argsort(chebyshev, kind="stable")[:n_changed]] = True
    moved = clean.copy()
    moved[changed, 0] += CORRIDOR_BOX_DEPTH
    std = float(np.sqrt(noise_variance))
    reference = clean + rng.normal(0.0, std, clean.shape)
    scan = moved + rng.normal(0.0, std, clean.shape)
    origin = np.array([0.0, 0.0, CORRIDOR_HEIGHT / 2.0])
    all_observed = np.ones(n_points, dtype=bool)
    return SyntheticPair(
        reference=reference,
        scan=scan,
        reference_changed=changed.copy(),
        scan_changed=changed.copy(),
        reference_observed=all_observed.copy(),
        scan_observed=all_observed.copy(),
        reference_origin=origin.copy(),
        scan_origin=origin.copy(),
        true_transform=np.eye(4),
    )


# --------------------------------------------------------------------------------------------
# Ray-cast lidar scene
# --------------------------------------------------------------------------------------------

ROOM_MIN = np.array([0.0, 0.0, 0.0])
ROOM_MAX = np.array([16.0, 8.0, 3.0])
"""The building's interior: room A is x in [0, 10], room B x in [10.2, 16], joined by a
doorway (y in [3.2, 4.4], z < 2.2) in the 0.2 m dividing wall."""

LIDAR_ELEVATION_DEG = (-30.0, 30.0)
"""Vertical field of view of the simulated spinning lidar (degrees above the horizontal)."""
LIDAR_RANGE = (0.3, 40.0)
"""Minimum and maximum range (metres) of the simulated lidar."""
LIDAR_ANISOTROPY = 2.0
"""Ring spacing / azimuth step: 2 like a 128-ring, 2048-column lidar (rings are sparser)."""
SENSOR_HEIGHT = 1.2
REFERENCE_SENSOR_XY = (4.6, 3.6)
MIN_SENSOR_CLEARANCE = 0.5
"""The scan sensor is placed at least this far (metres) from every object."""


@dataclass(frozen=True)
class SceneBox:
    """A solid axis-aligned box in the world (reference) frame.

    Attributes
    ----------
    name : str
    low, high : tuple of float
        Opposite corners (x, y, z), metres.
    """

    name: str
    low: tuple[float, float, float]
    high: tuple[float, float, float]

    @property
    def centre(self) -> NDArray[np.float64]:
        """Centre of the box, shape (3,)."""
        return (np.asarray(self.low) + np.asarray(self.high)) / 2.0


STATIC_BOXES: tuple[SceneBox, ...] = (
    SceneBox("dividing_wall_south", (10.0, 0.0, 0.0), (10.2, 3.2, 3.0)),
    SceneBox("dividing_wall_north", (10.0, 4.4, 0.0), (10.2, 8.0, 3.0)),
    SceneBox("door_lintel", (10.0, 3.2, 2.2), (10.2, 4.4, 3.0)),
    SceneBox("cabinet", (0.0, 1.0, 0.0), (0.6, 3.0, 1.9)),
    SceneBox("table", (6.0, 5.6, 0.0), (7.6, 6.6, 0.75)),
    SceneBox("pillar", (7.2, 2.4, 0.0), (7.6, 2.8, 3.0)),
    SceneBox("crate", (2.2, 6.2, 0.0), (3.0, 7.0, 0.9)),
    SceneBox("shelf", (4.0, 7.6, 0.0), (6.0, 8.0, 2.2)),
    SceneBox("box_room_b", (12.0, 1.0, 0.0), (13.0, 2.0, 1.2)),
    SceneBox("shelf_room_b", (13.0, 7.5, 0.0), (15.5, 8.0, 2.0)),
)
"""The furniture and the dividing wall of :func:`raycast_scene`, present in both worlds."""
_ADDED_BOX = SceneBox("added_box", (5.4, 1.2, 0.0), (6.2, 2.0, 0.9))
_REMOVED_BOX = SceneBox("removed_box", (2.0, 4.6, 0.0), (2.9, 5.4, 1.0))
_MOVED_BOX_BEFORE = SceneBox("moved_box_before", (6.6, 4.0, 0.0), (7.4, 4.6, 0.8))
_MOVED_BOX_AFTER = SceneBox("moved_box_after", (3.0, 1.0, 0.0), (3.8, 1.6, 0.8))


def raycast_scene_objects(change: str) -> tuple[list[SceneBox], list[SceneBox]]:
    """The changing objects of :func:`raycast_scene`, in the reference (= world) frame.

    Parameters
    ----------
    change : {"none", "box", "removed", "moved", "mixed"}

    Returns
    -------
    reference_only : list of SceneBox
        Objects present in the reference's world only (their points are "removed").
    scan_only : list of SceneBox
        Objects present in the scan's world only (their points are "added").
    """
    if change not in CHANGE_KINDS:
        raise ValueError(f"change must be one of {CHANGE_KINDS}, got {change!r}")
    reference_only: list[SceneBox] = []
    scan_only: list[SceneBox] = []
    if change in ("box", "mixed"):
        scan_only.append(_ADDED_BOX)
    if change in ("removed", "mixed"):
        reference_only.append(_REMOVED_BOX)
    if change in ("moved", "mixed"):
        reference_only.append(_MOVED_BOX_BEFORE)
        scan_only.append(_MOVED_BOX_AFTER)
    return reference_only, scan_only


def _box_arrays(boxes: list[SceneBox]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    low = np.array([box.low for box in boxes], dtype=np.float64).reshape(-1, 3)
    high = np.array([box.high for box in boxes], dtype=np.float64).reshape(-1, 3)
    return low, high


def _cast_rays(
    origin: NDArray[np.float64],
    directions: NDArray[np.float64],
    box_low: NDArray[np.float64],
    box_high: NDArray[np.float64],
    *,
    shell_low: NDArray[np.float64] = ROOM_MIN,
    shell_high: NDArray[np.float64] = ROOM_MAX,
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """First hit of rays from ``origin`` inside the room shell, with solid boxes in it.

    Parameters
    ----------
    origin : ndarray, shape (3,)
        Must lie inside the shell and outside every box.
    directions : ndarray, shape (r, 3)
        Unit ray directions.
    box_low, box_high : ndarray, shape (b, 3)
        Corners of the solid boxes.
    shell_low, shell_high : ndarray, shape (3,)
        Corners of the closed shell (default: this module's building).

    Returns
    -------
    distance : ndarray, shape (r,)
        Distance to the first surface hit (every ray hits the closed shell).
    hit_object : ndarray, shape (r,), int64
        Index of the box hit, or -1 for the shell (floor, walls, ceiling).
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse = 1.0 / directions
        # leaving the shell: the far slab of each axis
        to_max = (shell_high - origin) * inverse
        to_min = (shell_low - origin) * inverse
        exit_distance = np.where(inverse > 0, to_max, to_min)
        exit_distance = np.where(np.isfinite(exit_distance), exit_distance, np.inf).min(axis=1)
        distance = exit_distance
        hit_object = np.full(directions.shape[0], -1, dtype=np.int64)
        for index in range(box_low.shape[0]):
            t_low = (box_low[index] - origin) * inverse
            t_high = (box_high[index] - origin) * inverse
            t_near = np.fmin(t_low, t_high)
            t_far = np.fmax(t_low, t_high)
            # rays parallel to a slab give +-inf (or nan when the origin is on its plane)
            t_near = np.where(np.isnan(t_near), -np.inf, t_near).max(axis=1)
            t_far = np.where(np.isnan(t_far), np.inf, t_far).min(axis=1)
            hits = (t_near <= t_far) & (t_near > 0.0) & (t_near < distance)
            distance = np.where(hits, t_near, distance)
            hit_object[hits] = index
    return distance, hit_object


def _lidar_directions(n_rays: int, rng: np.random.Generator) -> NDArray[np.float64]:
    """Unit directions of one spinning-lidar sweep, shape (n_rays, 3).

    Rings evenly spaced over :data:`LIDAR_ELEVATION_DEG` (each with a small random elevation
    error), columns evenly spaced in azimuth with a random phase per ring and per-ray jitter of
    a quarter step; the ring spacing is :data:`LIDAR_ANISOTROPY` times the azimuth step.
    """
    low_deg, high_deg = LIDAR_ELEVATION_DEG
    span = high_deg - low_deg
    # n_rings * n_columns ~ n_rays with (span / n_rings) = anisotropy * (360 / n_columns)
    n_rings = max(4, round(np.sqrt(n_rays * span / (360.0 * LIDAR_ANISOTROPY))))
    n_columns = int(np.ceil(n_rays / n_rings))
    ring_step = span / n_rings
    ring_elevation = low_deg + ring_step * (np.arange(n_rings) + 0.5)
    ring_elevation += rng.normal(0.0, 0.05 * ring_step, n_rings)
    column_step = 360.0 / n_columns
    phase = rng.uniform(0.0, column_step, n_rings)
    azimuth = phase[:, None] + column_step * np.arange(n_columns)[None, :]
    azimuth = azimuth + rng.uniform(-0.25, 0.25, azimuth.shape) * column_step
    elevation = np.broadcast_to(ring_elevation[:, None], azimuth.shape)
    azimuth_rad = np.deg2rad(azimuth.ravel())
    elevation_rad = np.deg2rad(elevation.ravel())
    keep = np.sort(rng.choice(azimuth_rad.size, size=n_rays, replace=False))
    azimuth_rad = azimuth_rad[keep]
    elevation_rad = elevation_rad[keep]
    cos_elevation = np.cos(elevation_rad)
    return np.column_stack(
        [
            cos_elevation * np.cos(azimuth_rad),
            cos_elevation * np.sin(azimuth_rad),
            np.sin(elevation_rad),
        ]
    )


def _visible_from(
    origin: NDArray[np.float64],
    points: NDArray[np.float64],
    box_low: NDArray[np.float64],
    box_high: NDArray[np.float64],
    *,
    range_limits: tuple[float, float] = LIDAR_RANGE,
    elevation_deg: tuple[float, float] = LIDAR_ELEVATION_DEG,
    shell_low: NDArray[np.float64] = ROOM_MIN,
    shell_high: NDArray[np.float64] = ROOM_MAX,
) -> NDArray[np.bool_]:
    """Whether a sensor at ``origin`` sees the exact surface points ``points``, shape (p,).

    True iff the point is within the lidar's range and elevation field of view and the first
    surface a ray from ``origin`` towards it meets (in the world given by the boxes and the
    shell; by default this module's lidar and building) is not before the point.
    """
    offset = points - origin
    distance = np.linalg.norm(offset, axis=1)
    directions = offset / distance[:, None]
    elevation = np.rad2deg(np.arcsin(np.clip(directions[:, 2], -1.0, 1.0)))
    in_view = (
        (distance >= range_limits[0])
        & (distance <= range_limits[1])
        & (elevation >= elevation_deg[0])
        & (elevation <= elevation_deg[1])
    )
    first_hit, _ = _cast_rays(
        origin, directions, box_low, box_high, shell_low=shell_low, shell_high=shell_high
    )
    not_blocked = first_hit >= distance - (1e-7 + 1e-7 * distance)
    return in_view & not_blocked


def _random_rotation(angle_deg: float, rng: np.random.Generator) -> NDArray[np.float64]:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = np.deg2rad(angle_deg)
    cross = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * cross + (1.0 - np.cos(angle)) * (cross @ cross)


def _place_scan_sensor(
    sensor_shift: float, boxes: list[SceneBox], rng: np.random.Generator
) -> NDArray[np.float64]:
    reference_sensor = np.array([*REFERENCE_SENSOR_XY, SENSOR_HEIGHT])
    low, high = _box_arrays(boxes)
    for _ in range(200):
        heading = rng.uniform(0.0, 2.0 * np.pi)
        candidate = reference_sensor + sensor_shift * np.array(
            [np.cos(heading), np.sin(heading), 0]
        )
        inside_room = np.all(candidate > ROOM_MIN + MIN_SENSOR_CLEARANCE) and np.all(
            candidate < ROOM_MAX - MIN_SENSOR_CLEARANCE
        )
        gap = np.maximum(np.maximum(low - candidate, candidate - high), 0.0)
        clear = np.linalg.norm(gap, axis=1).min() >= MIN_SENSOR_CLEARANCE
        if inside_room and clear:
            return candidate
    raise ValueError(
        f"no free sensor position {sensor_shift} m from the reference sensor; "
        "use a smaller sensor_shift (<= 1.5 m works)"
    )


def raycast_scene(
    *,
    n_points: int = 200_000,
    change: str = "box",
    range_noise: float = 0.01,
    sensor_shift: float = 1.0,
    pose_error: tuple[float, float] = (0.0, 0.0),
    random_state: int | np.random.Generator | None = None,
) -> SyntheticPair:
    """A ray-cast lidar rescan of two furnished rooms, with exact ground truth.

    The world (metres, the reference frame): a 16 x 8 x 3 m building split by a 0.2 m wall
    with a doorway into room A (x < 10) and room B (x > 10.2); a cabinet, table, pillar,
    crate and shelf in room A and two more objects in room B, all solid boxes standing on the
    floor or against walls.  The lidar (elevation -30 to +30 degrees, full turn in azimuth,
    range 0.3-40 m, rings twice as far apart as columns, random phase and jitter) sits 1.2 m
    above the floor at (4.6, 3.6) for the reference; the scan's sensor is ``sensor_shift``
    metres away horizontally in a random free direction.  Each scan casts ``n_points`` rays
    and keeps every hit (the building is closed), so density falls with range and furniture
    casts shadows.  Range noise is Gaussian along each ray.

    Changes (see :func:`raycast_scene_objects` for the boxes): ``"box"`` adds a 0.8 x 0.8 x
    0.9 m box; ``"removed"`` removes a 0.9 x 0.8 x 1.0 m box; ``"moved"`` moves a 0.8 x 0.6 x
    0.8 m box about 4.9 m; ``"mixed"`` does all three.  Changed points are points on a changed
    object.  Observed masks come from casting exact rays from the *other* sensor towards each
    noise-free hit in the other world: e.g. the floor under an added box and the wall behind
    it are unobserved in the reference; points on a removed object are observed (the scan's
    rays pass through where it stood) and changed.

    The pose error rotates the scan by ``pose_error[1]`` degrees about a random axis through
    its sensor and translates it by ``pose_error[0]`` metres in a random direction;
    ``true_transform`` undoes this.

    Parameters
    ----------
    n_points : int
        Rays (and points) per scan, >= 1000.  200k generate in well under 2 s.
    change : {"none", "box", "removed", "moved", "mixed"}
    range_noise : float
        Standard deviation (metres) of the range noise.
    sensor_shift : float
        Distance (metres) between the two sensor positions, <= ~1.5.
    pose_error : (float, float)
        (translation in metres, rotation in degrees) applied to the scan.
    random_state : int, Generator or None

    Returns
    -------
    SyntheticPair
        ``n == m == n_points``.
    """
    if n_points < 1000:
        raise ValueError(f"n_points must be at least 1000, got {n_points}")
    if range_noise < 0:
        raise ValueError(f"range_noise must be >= 0, got {range_noise}")
    rng = np.random.default_rng(random_state)
    reference_only, scan_only = raycast_scene_objects(change)
    reference_world = [*STATIC_BOXES, *reference_only]
    scan_world = [*STATIC_BOXES, *scan_only]
    reference_sensor = np.array([*REFERENCE_SENSOR_XY, SENSOR_HEIGHT])
    scan_sensor = _place_scan_sensor(
        sensor_shift, [*STATIC_BOXES, *reference_only, *scan_only], rng
    )
    reference_low, reference_high = _box_arrays(reference_world)
    scan_low, scan_high = _box_arrays(scan_world)
    n_static = len(STATIC_BOXES)

    def sweep(sensor, low, high):
        directions = _lidar_directions(n_points, rng)
        distance, hit_object = _cast_rays(sensor, directions, low, high)
        exact = sensor + distance[:, None] * directions
        noisy = sensor + (distance + rng.normal(0.0, range_noise, distance.shape))[:, None] * (
            directions
        )
        return exact, noisy, hit_object >= n_static

    reference_exact, reference_points, reference_changed = sweep(
        reference_sensor, reference_low, reference_high
    )
    scan_exact, scan_points_world, scan_changed = sweep(scan_sensor, scan_low, scan_high)
    reference_observed = _visible_from(scan_sensor, reference_exact, scan_low, scan_high)
    scan_observed = _visible_from(reference_sensor, scan_exact, reference_low, reference_high)

    translation_m, rotation_deg = pose_error
    rotation = _random_rotation(rotation_deg, rng)
    direction = rng.normal(size=3)
    translation = translation_m * direction / np.linalg.norm(direction)
    # scan frame = rotation about the scan sensor, then translation
    pose = np.eye(4)
    pose[:3, :3] = rotation
    pose[:3, 3] = scan_sensor - rotation @ scan_sensor + translation
    true_transform = np.linalg.inv(pose)
    return SyntheticPair(
        reference=reference_points,
        scan=_transform_points(scan_points_world, pose),
        reference_changed=reference_changed,
        scan_changed=scan_changed,
        reference_observed=reference_observed,
        scan_observed=scan_observed,
        reference_origin=reference_sensor,
        scan_origin=_transform_points(scan_sensor[None, :], pose)[0],
        true_transform=true_transform,
    )
