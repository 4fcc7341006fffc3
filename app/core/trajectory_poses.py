"""Where the moving sensor was for each point of a cloud taken along a trajectory.

With per-point times, a point's sensor position is the trajectory interpolated at its time
(linear in position).  Without them, each point takes the nearest pose from which it is in line
of sight within the sensor's range: the cloud is cut into small cells, and each cell's centre
is tried against its nearest poses, nearest first, the first whose segment to the cell crosses
no occupied voxel of the cloud winning (the nearest pose when none is clear).  The points are
then grouped into pseudo-stations, consecutive stretches of the path over which the sensor moved
at most ``group_length``: the ray visibility test runs per group from its mean sensor position
(:mod:`app.core.localise.trajectory_visibility`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.cloud import PointCloud
from app.core.trajectory import Trajectory, TrajectoryError

__all__ = [
    "SensorGroups",
    "interpolate_positions",
    "line_of_sight_poses",
    "sensor_groups",
    "with_trajectory",
]

TIME_TOLERANCE = 0.05
"""Seconds a point's time may lie outside the trajectory's span (or a pose step, if longer)."""
MOST_OUTSIDE_SHARE = 0.5
"""More than this share of points outside the trajectory's span: the trajectory does not fit."""
GROUP_LENGTH = 0.05
"""Metres the sensor may move within one pseudo-station."""
MAX_GROUPS = 4096
"""Most pseudo-stations per cloud (a longer path gets longer groups): bounds the test's cost."""
SENSOR_RANGE = 30.0
"""Metres: poses farther than this from a point are not candidates to have seen it."""
LINE_OF_SIGHT_POSES = 6
"""Nearest poses tried per cell, nearest first."""
CELL_FACTOR = 4.0
"""Line-of-sight cells are this many voxels wide (points in a cell share their pose)."""
CLEARANCE_VOXELS = 2.0
"""The last voxels before a cell (its own surface) are not checked for blocking."""


@dataclass(frozen=True)
class SensorGroups:
    """A cloud's points cut into pseudo-stations along its trajectory.

    Attributes
    ----------
    origins : ndarray, shape (k, 3), float64
        Each group's mean sensor position, in the points' frame.
    group : ndarray, shape (n,), int64
        Each point's group (index into ``origins``).
    report : dict
        ``{"source": "trajectory", "poses", "time_span", "points_outside", "assignment",
        "groups"}`` (JSON-serialisable).
    """

    origins: NDArray[np.float64]
    group: NDArray[np.int64]
    report: dict[str, Any] = field(default_factory=dict)


def interpolate_positions(
    trajectory: Trajectory, times: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """The sensor position at each time, linearly interpolated along the trajectory.

    Parameters
    ----------
    trajectory : Trajectory
        m poses with times.
    times : ndarray, shape (n,)
        The points' times (the trajectory's clock).

    Returns
    -------
    positions : ndarray, shape (n, 3), float64
        Times outside the span take the nearest end pose.
    outside : ndarray, shape (n,), bool
        Times outside the span by more than the tolerance (:data:`TIME_TOLERANCE` or one
        median pose step, the larger).

    Raises
    ------
    TrajectoryError
        The trajectory has no times, a time is not finite, or more than half the points lie
        outside the span (the message gives both spans).
    """
    if not trajectory.has_times:
        raise TrajectoryError(
            "the points have per-point times but the trajectory has none (KITTI poses without "
            "a times file or rate): give the poses' times"
        )
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    if not np.isfinite(times).all():
        raise TrajectoryError("the points' times have non-finite values: give finite times")
    pose_times = trajectory.times
    step = float(np.median(np.diff(pose_times))) if len(pose_times) > 1 else 0.0
    tolerance = max(TIME_TOLERANCE, step)
    outside = (times < pose_times[0] - tolerance) | (times > pose_times[-1] + tolerance)
    if times.size and outside.mean() > MOST_OUTSIDE_SHARE:
        raise TrajectoryError(
            "trajectory times do not cover the points' times: points span "
            f"{times.min():.6f}..{times.max():.6f}, trajectory {pose_times[0]:.6f}.."
            f"{pose_times[-1]:.6f} ({int(outside.sum())} of {times.size} points outside); give "
            "the trajectory recorded with this scan, on the same clock"
        )
    positions = np.column_stack(
        [np.interp(times, pose_times, trajectory.positions[:, axis]) for axis in range(3)]
    )
    return positions, outside


def _path_length(positions: NDArray[np.float64]) -> NDArray[np.float64]:
    """Distance travelled to each pose, shape (m,)."""
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def _voxel_keys(cells: NDArray[np.int64]) -> NDArray[np.int64]:
    """One int64 per (i, j, k) voxel (21 bits an axis, offset to non-negative)."""
    shifted = cells + (1 << 20)
    return (shifted[:, 0] << 42) | (shifted[:, 1] << 21) | shifted[:, 2]


def line_of_sight_poses(
    points: NDArray[np.float64],
    trajectory: Trajectory,
    *,
    voxel: float | None = None,
    sensor_range: float = SENSOR_RANGE,
) -> NDArray[np.int64]:
    """Each point's nearest pose from which it is in line of sight.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    trajectory : Trajectory
        m poses (their times are not used).
    voxel : float, optional
        Occupancy voxel (metres); default twice the cloud's median nearest-neighbour spacing
        (measured on a sample), at least 2 cm.
    sensor_range : float
        Poses farther than this are not tried.

    Returns
    -------
    ndarray, shape (n,), int64
        Index of the pose.  Cost is bounded: cells of :data:`CELL_FACTOR` voxels share their
        pose, at most :data:`LINE_OF_SIGHT_POSES` poses are tried per cell.
    """
    points = np.asarray(points, dtype=np.float64)
    poses = trajectory.positions
    if len(poses) == 1 or len(points) == 0:
        return np.zeros(len(points), dtype=np.int64)
    if voxel is None:
        sample = points[:: max(1, len(points) // 20_000)]
        distances, _ = KDTree(sample).query(sample, k=2)
        spacing = float(np.median(distances[:, 1])) * (len(sample) / len(points)) ** 0.5
        voxel = max(0.02, 2.0 * spacing)  # a surface sample: spacing grows as its square root
    low = points.min(axis=0) - voxel
    occupied = np.unique(_voxel_keys(np.floor((points - low) / voxel).astype(np.int64)))
    cell = CELL_FACTOR * voxel
    cell_of_point = np.floor((points - low) / cell).astype(np.int64)
    cell_keys, point_cell = np.unique(_voxel_keys(cell_of_point), return_inverse=True)
    centres = np.zeros((len(cell_keys), 3))
    np.add.at(centres, point_cell, points)
    centres /= np.bincount(point_cell, minlength=len(cell_keys))[:, None]
    k = min(LINE_OF_SIGHT_POSES, len(poses))
    distance, nearest = KDTree(poses).query(centres, k=k)
    distance = distance.reshape(len(centres), k)
    nearest = nearest.reshape(len(centres), k).astype(np.int64)
    chosen = nearest[:, 0].copy()
    open_cells = np.ones(len(centres), dtype=bool)
    for rank in range(k):
        rows = np.flatnonzero(open_cells & (distance[:, rank] <= sensor_range))
        if rows.size == 0:
            continue
        clear = _segments_clear(
            poses[nearest[rows, rank]], centres[rows], occupied, low, voxel, CLEARANCE_VOXELS
        )
        chosen[rows[clear]] = nearest[rows[clear], rank]
        open_cells[rows[clear]] = False
    return chosen[point_cell]


def _segments_clear(
    starts: NDArray[np.float64],
    ends: NDArray[np.float64],
    occupied: NDArray[np.int64],
    low: NDArray[np.float64],
    voxel: float,
    clearance: float,
) -> NDArray[np.bool_]:
    """Whether each segment (stopped ``clearance`` voxels short of its end) meets no occupied
    voxel, sampled every half voxel, shape (s,)."""
    clear = np.ones(len(starts), dtype=bool)
    offset = ends - starts
    length = np.linalg.norm(offset, axis=1)
    usable = np.maximum(length - clearance * voxel, 0.0)
    steps = np.ceil(usable / (0.5 * voxel)).astype(np.int64)
    chunk = 200_000
    order = np.argsort(steps)
    for start in range(0, len(order), 4096):
        rows = order[start : start + 4096]
        most = int(steps[rows].max()) if rows.size else 0
        if most == 0:
            continue
        for first in range(1, most + 1, max(1, chunk // len(rows))):
            samples = np.arange(first, min(most + 1, first + max(1, chunk // len(rows))))
            live = samples[None, :] <= steps[rows, None]
            fraction = samples[None, :] * (0.5 * voxel) / np.maximum(length[rows, None], 1e-12)
            where = starts[rows, None, :] + fraction[:, :, None] * offset[rows, None, :]
            keys = _voxel_keys(np.floor((where.reshape(-1, 3) - low) / voxel).astype(np.int64))
            found = np.searchsorted(occupied, keys)
            hit = occupied[np.minimum(found, len(occupied) - 1)] == keys
            blocked = (hit.reshape(live.shape) & live).any(axis=1)
            clear[rows[blocked]] = False
    return clear


def sensor_groups(
    points: NDArray[np.float64],
    trajectory: Trajectory,
    times: NDArray[np.float64] | None = None,
    *,
    group_length: float = GROUP_LENGTH,
    sensor_range: float = SENSOR_RANGE,
) -> SensorGroups:
    """Cut a cloud into pseudo-stations along its trajectory.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        In the trajectory's frame.
    trajectory : Trajectory
    times : ndarray, shape (n,), optional
        Per-point times (the cloud's ``"time"`` attribute): positions are interpolated; without
        them each point takes its nearest pose in line of sight (:func:`line_of_sight_poses`).
    group_length : float
        The sensor moves at most this far within a group (longer when the path would give more
        than :data:`MAX_GROUPS`).
    sensor_range : float

    Returns
    -------
    SensorGroups

    Raises
    ------
    TrajectoryError
        Times that the trajectory does not cover, or a trajectory without times for points
        with times (:func:`interpolate_positions`).
    """
    points = np.asarray(points, dtype=np.float64)
    travelled = _path_length(trajectory.positions)
    length = max(group_length, float(travelled[-1]) / MAX_GROUPS)
    report: dict[str, Any] = {
        "source": "trajectory",
        "poses": len(trajectory),
        "time_span": [float(trajectory.times[0]), float(trajectory.times[-1])]
        if trajectory.has_times
        else None,
        "path_length_m": float(travelled[-1]),
    }
    if times is not None:
        positions, outside = interpolate_positions(trajectory, times)
        along = np.interp(times, trajectory.times, travelled)
        report.update(assignment="times", points_outside=int(outside.sum()))
    else:
        pose = line_of_sight_poses(points, trajectory, sensor_range=sensor_range)
        positions = trajectory.positions[pose]
        along = travelled[pose]
        report.update(assignment="line_of_sight", points_outside=0)
    _, group = np.unique(np.floor(along / length).astype(np.int64), return_inverse=True)
    group = group.reshape(-1).astype(np.int64)
    count = int(group.max()) + 1 if group.size else 0
    origins = np.zeros((count, 3))
    np.add.at(origins, group, positions)
    origins /= np.maximum(np.bincount(group, minlength=count), 1)[:, None]
    report["groups"] = count
    report["group_length_m"] = length
    return SensorGroups(origins=origins, group=group, report=report)


def with_trajectory(cloud: PointCloud, trajectory: Trajectory) -> PointCloud:
    """``cloud`` with ``trajectory``, checked against its per-point times when it has them.

    Raises
    ------
    TrajectoryError
        The trajectory does not cover the points' times, or has no times while they do
        (:func:`interpolate_positions`).
    """
    times = cloud.attributes.get("time")
    if times is not None:
        interpolate_positions(trajectory, np.asarray(times, dtype=np.float64))
    return dataclasses.replace(cloud, trajectory=trajectory)
