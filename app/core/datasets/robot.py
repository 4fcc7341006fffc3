"""Robot / mobile laser scanning maps and terrestrial multi-station scans: issue 29's lidar classes.

Layouts (:data:`ROBOT_LAYOUTS`): a corridor 15-30 x 2.5-4 m with chairs, boxes and boards along
its walls; an office 8-14 x 6-10 m with desks, chairs, boxes and boards; a warehouse 15-30 x
12-20 x 5-8 m with rows of racks (solid, never changed) and boxes and boards in its aisles.

- **Robot maps** (:func:`robot_pair`): a 16-ring (+-15 degrees) or 32-ring (-25 to +15 degrees)
  lidar 0.5-1.8 m above the floor drives along a path (the corridor's length, a loop round the
  office, a serpentine through the warehouse's aisles) and sweeps every 0.3-1 m; each sweep is
  placed with its own pose error (3 mm a coordinate, 0.05 degrees), the sweeps are merged in the
  world frame and voxel-filtered at 2-5 cm.  The second epoch's path is another one: offset,
  run the other way, over another extent.
- **Terrestrial scans** (:func:`terrestrial_pair`): 2-4 stations a epoch of a dome lidar
  (:func:`app.core.datasets.lidar.lidar_directions`, -45 to 60 degrees), registered with 2 mm /
  0.01 degree errors, merged and thinned to 1-2 cm; the scan's stations are drawn anew.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from app.core.datasets.furniture import (
    MOVABLE_KINDS,
    MapObject,
    Placement,
    apply_change,
    make_object,
    place_object,
)
from app.core.datasets.lidar import ELEVATION_RANGE_DEG, LidarWorld, lidar_directions
from app.core.datasets.map_world import (
    EpochSamples,
    MapPair,
    SensorModel,
    SensorPath,
    assemble_pair,
    cast_rays,
    visible_enough,
    world_of,
)

__all__ = ["ROBOT_LAYOUTS", "robot_pair", "terrestrial_pair"]

ROBOT_LAYOUTS = ("corridor", "office", "warehouse")
"""Values of ``layout``."""
RINGS = {16: (-15.0, 15.0), 32: (-25.0, 15.0)}
"""Ring count: (lowest, highest) elevation in degrees."""
LIDAR_RANGE = (0.5, 60.0)
TLS_RANGE = (0.3, 120.0)
RANGE_NOISE = {"robot": 0.01, "tls": 0.004}
POSE_ERROR = {"robot": (0.003, 0.05), "tls": (0.002, 0.01)}
"""Per sweep or station: (standard deviation of each coordinate in metres, rotation degrees)."""
CLEARANCE = 0.5
"""Objects stay this far (metres, horizontally) from every path and station."""


def _polyline(waypoints: NDArray[np.float64], step: float) -> NDArray[np.float64]:
    """Points every ``step`` metres along the polyline through ``waypoints`` (w, 2), (q, 2)."""
    lengths = np.linalg.norm(np.diff(waypoints, axis=0), axis=1)
    along = np.concatenate([[0.0], np.cumsum(lengths)])
    samples = np.arange(0.0, along[-1] + 1e-9, step)
    return np.column_stack(
        [np.interp(samples, along, waypoints[:, 0]), np.interp(samples, along, waypoints[:, 1])]
    )


def _racks(
    rng: np.random.Generator, shell_high: NDArray[np.float64]
) -> tuple[list[MapObject], list[float]]:
    """Rows of racks along x with aisles between them, and the aisles' centre lines (y)."""
    aisle, depth = rng.uniform(2.8, 3.5), rng.uniform(0.9, 1.2)
    racks, aisles, y = [], [], 0.0
    while y + 2.0 * aisle + depth <= shell_high[1]:
        aisles.append(y + aisle / 2.0)
        height = min(rng.uniform(2.0, 4.5), shell_high[2] - 0.5)
        low = np.array([[3.0, y + aisle, 0.0]])
        high = np.array([[shell_high[0] - 3.0, y + aisle + depth, height]])
        racks.append(MapObject(f"rack {len(racks)}", "rack", low, high))
        y += aisle + depth
    aisles.append((y + shell_high[1]) / 2.0)
    return racks, aisles


def _waypoints(
    layout: str, rng: np.random.Generator, shell_high: NDArray, aisles: list[float], epoch: int
) -> NDArray[np.float64]:
    """Horizontal waypoints of one epoch's path; the second epoch runs the other way."""
    length, width = shell_high[0], shell_high[1]
    if layout == "corridor":
        start, end = rng.uniform(1.0, 0.25 * length), rng.uniform(0.75 * length, length - 1.0)
        lateral = width / 2.0 + rng.uniform(-0.25, 0.25, 3)
        points = np.column_stack([[start, (start + end) / 2.0, end], lateral])
    elif layout == "office":
        inset = rng.uniform(1.2, 2.0)
        corners = np.array(
            [
                [inset, inset],
                [length - inset, inset],
                [length - inset, width - inset],
                [inset, width - inset],
            ]
        )
        corners = np.roll(corners, int(rng.integers(4)), axis=0)
        loop = np.vstack([corners, corners[:1]])
        dense = _polyline(loop, 0.05)
        points = dense[: max(2, int(len(dense) * rng.uniform(0.7, 1.0)))]
    else:
        ends = (rng.uniform(1.2, 1.8), length - rng.uniform(1.2, 1.8))
        order = list(range(len(aisles)))
        rows = []
        for number, aisle in enumerate(order):
            y = aisles[aisle] + rng.uniform(-0.2, 0.2)
            rows += [[ends[number % 2], y], [ends[1 - number % 2], y]]
        points = np.array(rows)
    return points[::-1] if epoch == 1 else points


def _layout(
    layout: str, rng: np.random.Generator
) -> tuple[NDArray[np.float64], list[MapObject], list[float], dict[str, tuple[int, int]]]:
    """The shell's far corner, the fixed racks, the aisles and the furniture counts."""
    if layout == "corridor":
        shell = [rng.uniform(15.0, 30.0), rng.uniform(2.5, 4.0), rng.uniform(2.5, 3.2)]
        counts = {"chair": (1, 4), "box": (2, 5), "board": (1, 3)}
    elif layout == "office":
        shell = [rng.uniform(8.0, 14.0), rng.uniform(6.0, 10.0), rng.uniform(2.6, 3.2)]
        counts = {"desk": (2, 6), "chair": (3, 8), "box": (2, 5), "board": (1, 3)}
    elif layout == "warehouse":
        shell = [rng.uniform(15.0, 30.0), rng.uniform(12.0, 20.0), rng.uniform(5.0, 8.0)]
        counts = {"box": (4, 10), "board": (1, 3), "chair": (0, 2)}
    else:
        raise ValueError(f"layout must be one of {ROBOT_LAYOUTS}, got {layout!r}")
    shell_high = np.array(shell)
    racks, aisles = _racks(rng, shell_high) if layout == "warehouse" else ([], [])
    return shell_high, racks, aisles, counts


def _furnish(
    rng: np.random.Generator, placement: Placement, fixed: list[MapObject], counts: dict
) -> list[MapObject]:
    objects = list(fixed)
    for kind, (low, high) in counts.items():
        for number in range(int(rng.integers(low, high + 1))):
            template = make_object(f"{kind} {number}", kind, rng)
            placed = place_object(template, objects, placement, rng)
            if placed is not None:
                objects.append(placed)
    return objects


def _pose_errors(
    rng: np.random.Generator, count: int, kind: str
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per pose: an error rotation (c, 3, 3) of the stated angle and a translation (c, 3)."""
    shift, angle = POSE_ERROR[kind]
    axes = rng.normal(size=(count, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    return Rotation.from_rotvec(np.radians(angle) * axes).as_matrix(), rng.normal(
        0.0, shift, (count, 3)
    )


def _sweep(
    world_and_owner: tuple[LidarWorld, NDArray[np.int64]],
    path: SensorPath,
    local_directions: list[NDArray[np.float64]],
    kind: str,
    rng: np.random.Generator,
) -> EpochSamples:
    """Cast every pose's sweep (directions in the sensor frame), add range noise and pose
    errors; the returned path holds the poses as estimated (errors included)."""
    world = world_and_owner[0]
    directions = np.vstack(
        [
            local @ rotation.T
            for local, rotation in zip(local_directions, path.rotations, strict=True)
        ]
    )
    pose = np.repeat(np.arange(len(path.times)), [len(local) for local in local_directions])
    origins = path.positions[pose]
    distance, box = cast_rays(world, origins, directions, world_and_owner[1])
    limits = TLS_RANGE if kind == "tls" else LIDAR_RANGE
    keep = (distance >= limits[0]) & (distance <= limits[1])
    origins, directions, distance, box, pose = (
        origins[keep],
        directions[keep],
        distance[keep],
        box[keep],
        pose[keep],
    )
    exact = origins + distance[:, None] * directions
    measured = distance + rng.normal(0.0, RANGE_NOISE[kind], distance.shape)
    error_rotation, error_shift = _pose_errors(rng, len(path.times), kind)
    relative = np.einsum("pij,pj->pi", error_rotation[pose], measured[:, None] * directions)
    points = origins + error_shift[pose] + relative
    estimated = SensorPath(
        path.times,
        path.positions + error_shift,
        np.einsum("pij,pjk->pik", error_rotation, path.rotations),
    )
    return EpochSamples(points, exact, box, pose, estimated)


def _ring_directions(
    rings: int, azimuth_step_deg: float, count: int, rng: np.random.Generator
) -> list[NDArray[np.float64]]:
    """Each sweep's ray directions in the sensor frame (x forward, z up), a random phase each."""
    low, high = RINGS[rings]
    elevation = np.radians(np.linspace(low, high, rings))
    sweeps = []
    for _ in range(count):
        azimuth = np.radians(
            np.arange(0.0, 360.0, azimuth_step_deg) + rng.uniform(0, azimuth_step_deg)
        )
        grid_elevation, grid_azimuth = np.meshgrid(elevation, azimuth, indexing="ij")
        cos_elevation = np.cos(grid_elevation.ravel())
        sweeps.append(
            np.column_stack(
                [
                    cos_elevation * np.cos(grid_azimuth.ravel()),
                    cos_elevation * np.sin(grid_azimuth.ravel()),
                    np.sin(grid_elevation.ravel()),
                ]
            )
        )
    return sweeps


def _yaw_rotations(yaw: NDArray[np.float64]) -> NDArray[np.float64]:
    return Rotation.from_euler("z", yaw[:, None]).as_matrix().reshape(-1, 3, 3)


def robot_pair(
    *,
    layout: str = "corridor",
    change: str = "removed",
    misaligned: bool = False,
    rays_per_epoch: int = 150_000,
    voxel: float | None = None,
    visibility_stride: int | None = None,
    random_state: int = 0,
) -> MapPair:
    """A random two-epoch robot (mobile laser scanning) map, with per-point truth.

    Parameters
    ----------
    layout : {"corridor", "office", "warehouse"}
    change : {"none", "removed", "added", "moved", "rotated", "mixed"}
    misaligned : bool
        Give the scan turned by 0.3 degrees and shifted by 2-3 cm.
    rays_per_epoch : int
        About this many rays are cast per epoch: the azimuth step follows from it (at least
        0.1 degrees), the sweep spacing (0.3-1 m) and the ring count being drawn.
    voxel : float, optional
        Edge of the thinning voxels (metres); default drawn in 2-5 cm.
    visibility_stride : int, optional
        The truth's ``scored`` tests every this many sweeps of the other epoch; default: about
        :data:`~app.core.datasets.map_world.TESTED_POSES` sweeps spread along the path.
    random_state : int

    Returns
    -------
    MapPair
        ``map_class`` ``"robot"``; a changed pair has at least
        :data:`~app.core.datasets.map_world.MIN_VISIBLE_CHANGE` changed, scored points.
    """
    rng = np.random.default_rng(random_state)
    for _ in range(10):
        pair = _draw(
            "robot", layout, change, misaligned, rays_per_epoch, voxel, visibility_stride, rng
        )
        if visible_enough(pair):
            return replace(pair, seed=random_state)
    raise ValueError(f"no visible {change!r} change in 10 layouts; try another seed")


def terrestrial_pair(
    *,
    layout: str = "office",
    change: str = "removed",
    misaligned: bool = False,
    rays_per_epoch: int = 150_000,
    voxel: float | None = None,
    random_state: int = 0,
) -> MapPair:
    """A random two-epoch terrestrial survey (2-4 registered stations a epoch), with truth.

    Parameters are those of :func:`robot_pair`; ``voxel`` defaults to a draw in 1-2 cm and
    every station is tested for ``scored``.  ``map_class`` is ``"tls"``.
    """
    rng = np.random.default_rng(random_state)
    for _ in range(10):
        pair = _draw("tls", layout, change, misaligned, rays_per_epoch, voxel, 1, rng)
        if visible_enough(pair):
            return replace(pair, seed=random_state)
    raise ValueError(f"no visible {change!r} change in 10 layouts; try another seed")


def _stations(
    rng: np.random.Generator, shell_high: NDArray, aisles: list[float], count: int
) -> NDArray[np.float64]:
    """Horizontal station positions spread over the free floor (in the aisles of a warehouse)."""
    positions = []
    for number in range(count):
        x = shell_high[0] * (number + rng.uniform(0.2, 0.8)) / count
        x = float(np.clip(x, 1.0, shell_high[0] - 1.0))
        if aisles:
            y = aisles[int(rng.integers(len(aisles)))] + rng.uniform(-0.3, 0.3)
        else:
            y = rng.uniform(1.0, shell_high[1] - 1.0)
        positions.append([x, y])
    return np.array(positions)


def _draw(
    kind: str,
    layout: str,
    change: str,
    misaligned: bool,
    rays_per_epoch: int,
    voxel: float | None,
    stride: int | None,
    rng: np.random.Generator,
) -> MapPair:
    shell_high, racks, aisles, counts = _layout(layout, rng)
    shell = (np.zeros(3), shell_high)
    if kind == "robot":
        rings = int(rng.choice(list(RINGS)))
        spacing, speed = rng.uniform(0.3, 1.0), rng.uniform(0.5, 1.2)
        height = rng.uniform(0.5, 1.8)
        horizontal = [_waypoints(layout, rng, shell_high, aisles, epoch) for epoch in (0, 1)]
        keep_out = np.vstack([_polyline(points, 0.1) for points in horizontal])
        tracks = [_polyline(points, spacing) for points in horizontal]
        sensor = SensorModel("lidar", LIDAR_RANGE, 180.0, RINGS[rings])
        metadata = {"rings": float(rings), "spacing": spacing, "height": height}
    else:
        count = int(rng.integers(2, 5))
        tracks = [_stations(rng, shell_high, aisles, count) for _ in (0, 1)]
        keep_out = np.vstack(tracks)
        height, speed = rng.uniform(1.2, 1.7), 0.0
        sensor = SensorModel("lidar", TLS_RANGE, 180.0, ELEVATION_RANGE_DEG)
        metadata = {"stations": float(count), "height": height}
    placement = Placement(shell[0], shell_high, keep_out, clearance=CLEARANCE, desk_share=0.3)
    objects = _furnish(rng, placement, racks, counts)

    def new_object(name: str) -> MapObject:
        kind_drawn = str(rng.choice(MOVABLE_KINDS))
        return make_object(f"{name} {kind_drawn}", kind_drawn, rng)

    scan_objects, changes = apply_change(change, objects, placement, rng, new_object)
    samples = []
    for epoch, (track, epoch_objects) in enumerate(
        zip(tracks, (objects, scan_objects), strict=True)
    ):
        start = 100.0 + 10_000.0 * epoch
        positions = np.column_stack([track, np.full(len(track), height)])
        if kind == "robot":
            step = np.gradient(track, axis=0) if len(track) > 1 else np.array([[1.0, 0.0]])
            yaw = np.arctan2(step[:, 1], step[:, 0])
            times = start + np.arange(len(track)) * spacing / speed
            azimuth_step = max(0.1, 360.0 * rings * len(track) / rays_per_epoch)
            local = _ring_directions(rings, azimuth_step, len(track), rng)
        else:
            yaw = rng.uniform(0.0, 2.0 * np.pi, len(track))
            times = start + 600.0 * np.arange(len(track))
            grid_step = float(np.sqrt(105.0 * 360.0 * len(track) / rays_per_epoch))
            local = [lidar_directions(grid_step, grid_step, 0.0) for _ in track]
        path = SensorPath(times, positions, _yaw_rotations(yaw))
        samples.append(_sweep(world_of(shell, epoch_objects), path, local, kind, rng))
    default_voxel = rng.uniform(0.02, 0.05) if kind == "robot" else rng.uniform(0.01, 0.02)
    voxel_size = float(default_voxel if voxel is None else voxel)
    metadata["voxel"] = voxel_size
    return assemble_pair(
        shell=shell,
        reference_objects=objects,
        scan_objects=scan_objects,
        changes=changes,
        samples=(samples[0], samples[1]),
        sensor=sensor,
        voxel=voxel_size,
        stride=stride,
        misaligned=misaligned,
        rng=rng,
        labels={
            "map_class": kind,
            "layout": layout,
            "change": change,
            "seed": 0,
            "metadata": metadata,
        },
    )
