"""Where the moving sensor was for each point of a cloud taken along a trajectory.

With per-point times, a point's sensor position is the trajectory interpolated at its time
(linear in position).  Without them, each point takes the nearest pose from which it is in line
of sight within the sensor's range: each pose's coarse depth image of the points near it says
which of them nothing hides from it (the nearest pose when none does).  The points are
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
LINE_OF_SIGHT_POSES = 8
"""Nearest poses tried per point, nearest first (each one it sees gets it as a ray)."""
LINE_OF_SIGHT_SAMPLE = 250_000
"""Most points whose line of sight is checked (evenly spread; they are the rays): bounds the
cost of clouds without times (the others take their nearest pose)."""
DEPTH_BIN_DEG = 1.5
"""Bins (degrees of azimuth and elevation) of the depth images line of sight is read from."""
SPLAT_FACTOR = 1.5
"""A point hides the bins within this many spacings of it (sampling leaves holes)."""
MAX_SPLAT_BINS = 4
DEPTH_BLOCK_POSES = 64
"""Depth images built at a time (64 x 29k bins of float32: 7 MB)."""
"""A point near a pose hides at most this many bins around its own (its spacing's width)."""
DEPTH_TOLERANCE = 0.05
DEPTH_RELATIVE_TOLERANCE = 0.1
"""A point sees a pose when its range is at most 1.1 x the bin's nearest range + 5 cm."""


@dataclass(frozen=True)
class SensorGroups:
    """A cloud's points cut into pseudo-stations along its trajectory.

    Attributes
    ----------
    origins : ndarray, shape (k, 3), float64
        Each group's mean sensor position, in the points' frame.
    group : ndarray, shape (n,), int64
        Each point's group (index into ``origins``).
    returns : ndarray, shape (r,), int64
        The points each group's rays end on, group after group (without times a point is a
        ray of the group of every pose in line of sight of it; with times of its own group).
    bounds : ndarray, shape (k + 1,), int64
        Group g's returns are ``returns[bounds[g]:bounds[g + 1]]``.
    report : dict
        ``{"source": "trajectory", "poses", "time_span", "points_outside", "assignment",
        "groups"}`` (JSON-serialisable).
    """

    origins: NDArray[np.float64]
    group: NDArray[np.int64]
    returns: NDArray[np.int64]
    bounds: NDArray[np.int64]
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


def _spacing(points: NDArray[np.float64]) -> float:
    """The cloud's median nearest-neighbour spacing, from a sample of at most 20k points."""
    sample = points[:: max(1, len(points) // 20_000)]
    distances, _ = KDTree(sample).query(sample, k=2)
    # a surface sample: its spacing grows as the square root of the thinning
    return float(np.median(distances[:, 1])) * (len(sample) / len(points)) ** 0.5


def line_of_sight(
    points: NDArray[np.float64],
    trajectory: Trajectory,
    *,
    sensor_range: float = SENSOR_RANGE,
    poses_tried: int = LINE_OF_SIGHT_POSES,
) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """Which of its nearest poses each point is in line of sight of.

    Each point is paired with its ``poses_tried`` nearest poses; each pose gets a coarse
    depth image (:data:`DEPTH_BIN_DEG` bins of azimuth and elevation) of the points paired
    with it, each bin holding its nearest range.  A point sees a pose when its range is at most
    the nearest range in its bin (within :data:`DEPTH_TOLERANCE` and
    :data:`DEPTH_RELATIVE_TOLERANCE` of it): nothing paired with that pose lies clearly in
    front of it (and it lies within ``sensor_range``).  Cost: ``n * poses_tried`` pairs.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    trajectory : Trajectory
        m poses (their times are not used).
    sensor_range : float
        Poses farther than this are not tried.
    poses_tried : int

    Returns
    -------
    nearest : ndarray, shape (n, k), int64
        Each point's k = min(poses_tried, m) nearest poses, nearest first.
    sees : ndarray, shape (n, k), bool
        Whether the point is in line of sight of each.
    """
    points = np.asarray(points, dtype=np.float64)
    poses = trajectory.positions
    count = points.shape[0]
    if len(poses) == 1 or count == 0:
        return np.zeros((count, 1), dtype=np.int64), np.ones((count, 1), dtype=bool)
    k = min(poses_tried, len(poses))
    distance, nearest = KDTree(poses).query(points, k=k)
    distance = np.asarray(distance, dtype=np.float64).reshape(count, k)
    nearest = np.asarray(nearest, dtype=np.int64).reshape(count, k)
    bin_size = np.radians(DEPTH_BIN_DEG)
    azimuth_bins = int(np.ceil(2 * np.pi / bin_size))
    elevation_bins = int(np.ceil(np.pi / bin_size)) + 1
    azimuth = np.empty((count, k), dtype=np.int64)
    elevation = np.empty((count, k), dtype=np.int64)
    for start in range(0, count, 250_000):
        rows = slice(start, start + 250_000)
        offset = points[rows, None, :] - poses[nearest[rows]]
        horizontal = np.hypot(offset[..., 0], offset[..., 1])
        azimuth[rows] = np.floor((np.arctan2(offset[..., 1], offset[..., 0]) + np.pi) / bin_size)
        elevation[rows] = np.floor((np.arctan2(offset[..., 2], horizontal) + np.pi / 2) / bin_size)
    azimuth %= azimuth_bins
    per_pose = azimuth_bins * elevation_bins
    cell = (elevation * azimuth_bins + azimuth).reshape(-1)
    pair_range = distance.reshape(-1).astype(np.float32)
    pair_pose = nearest.reshape(-1)
    # a near point hides the bins its surface patch covers, not only its own: it is splatted
    # over the bins within SPLAT_FACTOR spacings of it (at most MAX_SPLAT_BINS away)
    reach = np.minimum(
        np.ceil(SPLAT_FACTOR * _spacing(points) / (np.maximum(pair_range, 1e-6) * bin_size)) - 1,
        MAX_SPLAT_BINS,
    ).astype(np.int64)
    front = np.empty(pair_range.size, dtype=np.float32)
    image = np.full(DEPTH_BLOCK_POSES * per_pose, np.inf, dtype=np.float32)
    block_of_pair = pair_pose // DEPTH_BLOCK_POSES
    for block in np.unique(block_of_pair):  # the depth images of a block of poses at a time
        pairs = np.flatnonzero(block_of_pair == block)
        base = (pair_pose[pairs] - block * DEPTH_BLOCK_POSES) * per_pose
        np.minimum.at(image, base + cell[pairs], pair_range[pairs])
        for ring in range(1, MAX_SPLAT_BINS + 1):
            near = np.flatnonzero(reach[pairs] >= ring)
            if near.size == 0:
                break
            chosen = pairs[near]
            steps = range(-ring, ring + 1)
            for shift_azimuth in steps:
                for shift_elevation in steps:
                    if max(abs(shift_azimuth), abs(shift_elevation)) != ring:
                        continue
                    moved = (
                        np.clip(
                            elevation.reshape(-1)[chosen] + shift_elevation, 0, elevation_bins - 1
                        )
                        * azimuth_bins
                        + (azimuth.reshape(-1)[chosen] + shift_azimuth) % azimuth_bins
                    )
                    np.minimum.at(image, base[near] + moved, pair_range[chosen])
        front[pairs] = image[base + cell[pairs]]
        image.fill(np.inf)
    front = front.reshape(count, k)
    sees = (distance <= front * (1 + DEPTH_RELATIVE_TOLERANCE) + DEPTH_TOLERANCE) & (
        distance <= sensor_range
    )
    return nearest, sees


def line_of_sight_poses(
    points: NDArray[np.float64],
    trajectory: Trajectory,
    *,
    sensor_range: float = SENSOR_RANGE,
    poses_tried: int = LINE_OF_SIGHT_POSES,
) -> NDArray[np.int64]:
    """Each point's nearest pose from which it is in line of sight (:func:`line_of_sight`;
    its nearest pose when it sees none), shape (n,), int64."""
    nearest, sees = line_of_sight(
        points, trajectory, sensor_range=sensor_range, poses_tried=poses_tried
    )
    rank = np.where(sees.any(axis=1), np.argmax(sees, axis=1), 0)  # nearest first
    return nearest[np.arange(nearest.shape[0]), rank]


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
    else:  # line of sight of a sample of points (they are the rays), the nearest pose else
        sampled = np.arange(0, len(points), -(-len(points) // LINE_OF_SIGHT_SAMPLE))
        _, pose = KDTree(trajectory.positions).query(points, k=1)
        pose = np.asarray(pose, dtype=np.int64).reshape(-1)
        nearest, sees = line_of_sight(points[sampled], trajectory, sensor_range=sensor_range)
        rank = np.where(sees.any(axis=1), np.argmax(sees, axis=1), 0)  # nearest seen first
        pose[sampled] = nearest[np.arange(nearest.shape[0]), rank]
        positions = trajectory.positions[pose]
        along = travelled[pose]
        report.update(assignment="line_of_sight", points_outside=0)
    point_stretch = np.floor(along / length).astype(np.int64)
    used, group = np.unique(point_stretch, return_inverse=True)
    group = group.reshape(-1).astype(np.int64)
    count = int(group.max()) + 1 if group.size else 0
    member_point, member_group = np.arange(group.size), group
    if times is None:  # a ray from the group of every pose in line of sight (with points)
        seen_point, seen_rank = np.nonzero(sees)
        seen_stretch = np.floor(travelled[nearest[seen_point, seen_rank]] / length)
        slot = np.minimum(np.searchsorted(used, seen_stretch.astype(np.int64)), used.size - 1)
        known = used[slot] == seen_stretch
        pairs = np.unique(
            np.concatenate([group[sampled], slot[known]]) * group.size
            + np.concatenate([sampled, sampled[seen_point[known]]])
        )
        member_group, member_point = np.divmod(pairs, max(group.size, 1))
    order = np.argsort(member_group, kind="stable")
    bounds = np.searchsorted(member_group[order], np.arange(count + 1)).astype(np.int64)
    origins = np.zeros((count, 3))
    np.add.at(origins, group, positions)
    origins /= np.maximum(np.bincount(group, minlength=count), 1)[:, None]
    report["groups"] = count
    report["group_length_m"] = length
    report["rays"] = int(member_point.size)
    return SensorGroups(
        origins=origins,
        group=group,
        returns=member_point[order].astype(np.int64),
        bounds=bounds,
        report=report,
    )


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
