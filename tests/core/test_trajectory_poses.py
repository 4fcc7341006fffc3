"""Per-point sensor positions along a trajectory, and the pseudo-stations cut from them.

Rules checked: with times, positions are the trajectory interpolated linearly; points outside
the span by more than the tolerance are counted, and when most are outside the error gives both
spans; a trajectory without times cannot place points with times; without times each point
takes the nearest pose in line of sight (not one behind a wall, even when nearer); groups are
stretches of the path no longer than the group length, with their mean sensor positions;
without times a point is a ray of every pose that sees it, with times of its own group; a lone
sighting is one pseudo-station seeing through a place others saw otherwise.
"""

from __future__ import annotations

import numpy as np
import pytest

from app.core.cloud import PointCloud
from app.core.localise.rays import (
    STATUS_EDGE_ON,
    STATUS_SEEN_THROUGH,
    STATUS_SURFACE,
    STATUS_UNOBSERVED,
)
from app.core.localise.trajectory_visibility import lone_sightings
from app.core.trajectory import Trajectory, TrajectoryError
from app.core.trajectory_poses import (
    interpolate_positions,
    line_of_sight_poses,
    sensor_groups,
    with_trajectory,
)

LINE = Trajectory(
    np.array([10.0, 11.0, 12.0, 14.0]),
    np.array([[0.0, 0, 1], [1.0, 0, 1], [2.0, 0, 1], [2.0, 2.0, 1]]),
)


def test_positions_are_interpolated_linearly_at_the_points_times() -> None:
    positions, outside = interpolate_positions(LINE, np.array([10.0, 10.25, 11.5, 13.0, 14.0]))

    np.testing.assert_allclose(
        positions, [[0, 0, 1], [0.25, 0, 1], [1.5, 0, 1], [2.0, 1.0, 1], [2.0, 2.0, 1]]
    )
    assert not outside.any()


def test_points_outside_the_span_are_counted_and_most_outside_is_an_error() -> None:
    times = np.concatenate([np.linspace(10, 14, 8), [20.0, 30.0]])
    positions, outside = interpolate_positions(LINE, times)

    assert outside.sum() == 2
    np.testing.assert_allclose(positions[-1], LINE.positions[-1])  # clamped to the end
    with pytest.raises(TrajectoryError, match=r"points span 100\.0+\.\.200\.0+, trajectory 10"):
        interpolate_positions(LINE, np.linspace(100, 200, 10))


def test_a_trajectory_without_times_cannot_place_points_with_times() -> None:
    untimed = Trajectory(np.arange(4.0), LINE.positions, has_times=False)
    cloud = PointCloud.from_array(
        np.random.default_rng(0).uniform(0, 1, (50, 3)), {"time": np.linspace(10, 14, 50)}
    )

    with pytest.raises(TrajectoryError, match="trajectory has none"):
        interpolate_positions(untimed, np.array([1.0]))
    with pytest.raises(TrajectoryError, match="trajectory has none"):
        with_trajectory(cloud, untimed)
    assert with_trajectory(cloud, LINE).trajectory is LINE


def wall_scene() -> tuple[np.ndarray, Trajectory]:
    """A wall in the plane x = 0 (|y| <= 3, 0 <= z <= 2), a floor patch behind it at x = 0.5,
    and two poses: one 0.3 m in front of the wall (x = -0.3), one 1.5 m behind it (x = 2)."""
    grid = np.mgrid[-3:3:0.05, 0:2:0.05].reshape(2, -1).T
    wall = np.column_stack([np.zeros(len(grid)), grid])
    patch_grid = np.mgrid[0.3:0.8:0.05, -0.5:0.5:0.05].reshape(2, -1).T
    patch = np.column_stack([patch_grid, np.zeros(len(patch_grid))])
    poses = Trajectory(np.array([0.0, 1.0]), np.array([[-0.3, 0.0, 1.0], [2.0, 0.0, 1.0]]))
    return np.vstack([wall, patch]), poses


def test_without_times_a_point_takes_the_nearest_pose_that_sees_it() -> None:
    points, poses = wall_scene()
    on_patch = points[:, 0] > 0.2

    pose = line_of_sight_poses(points, poses)  # voxel: twice the spacing

    # the patch is nearer the pose in front of the wall, but only the one behind it sees it
    nearest = np.argmin(np.linalg.norm(points[on_patch, None] - poses.positions[None], axis=2), 1)
    assert (nearest == 0).mean() > 0.5
    assert (pose[on_patch] == 1).all()


def test_groups_are_short_stretches_of_the_path_with_their_mean_position() -> None:
    times = np.linspace(10, 13.99, 400)  # the path's last stretch ends before its end
    points = np.random.default_rng(1).uniform(-5, 5, (400, 3))

    groups = sensor_groups(points, LINE, times, group_length=0.5)

    assert groups.report["source"] == "trajectory"
    assert groups.report["assignment"] == "times"
    assert groups.report["poses"] == 4 and groups.report["time_span"] == [10.0, 14.0]
    assert groups.origins.shape == (8, 3)  # 4 m of path in 0.5 m stretches
    positions, _ = interpolate_positions(LINE, times)
    for number, origin in enumerate(groups.origins):
        mine = positions[groups.group == number]
        np.testing.assert_allclose(origin, mine.mean(axis=0))
        assert np.linalg.norm(mine - origin, axis=1).max() <= 0.5


def test_without_times_each_point_is_a_ray_of_every_pose_that_sees_it() -> None:
    points, poses = wall_scene()
    on_patch = np.flatnonzero(points[:, 0] > 0.2)
    # the wall (a sheet) in front of both poses: its part facing them squarely
    on_wall = np.flatnonzero(
        (points[:, 0] == 0.0) & (np.abs(points[:, 1]) < 0.5) & (np.abs(points[:, 2] - 1.0) < 0.5)
    )

    groups = sensor_groups(points, poses, group_length=0.05)

    assert groups.report["assignment"] == "line_of_sight"
    rays = [
        set(groups.returns[groups.bounds[number] : groups.bounds[number + 1]].tolist())
        for number in range(len(groups.origins))
    ]
    front = int(np.argmin(groups.origins[:, 0]))  # the group of the pose in front of the wall
    behind = 1 - front
    assert rays[behind] >= set(on_patch.tolist())  # the patch: only from behind the wall
    assert not rays[front] & set(on_patch.tolist())
    assert len(rays[front] & rays[behind] & set(on_wall.tolist())) > 0.9 * on_wall.size
    assert groups.report["rays"] == sum(len(ray) for ray in rays)


def test_with_times_each_point_is_a_ray_of_its_own_group_only() -> None:
    times = np.linspace(10, 13.99, 400)
    points = np.random.default_rng(2).uniform(-5, 5, (400, 3))

    groups = sensor_groups(points, LINE, times, group_length=0.5)

    for number in range(len(groups.origins)):
        returns = groups.returns[groups.bounds[number] : groups.bounds[number + 1]]
        np.testing.assert_array_equal(np.sort(returns), np.flatnonzero(groups.group == number))


def test_a_lone_sighting_is_one_pseudo_station_through_while_others_saw_the_place() -> None:
    through, surface, edge_on, none = (
        STATUS_SEEN_THROUGH,
        STATUS_SURFACE,
        STATUS_EDGE_ON,
        STATUS_UNOBSERVED,
    )
    statuses = np.array(
        [
            [through, through, through, through, through],
            [edge_on, through, none, surface, none],
            [none, none, none, none, none],
        ],
        dtype=np.int8,
    )

    np.testing.assert_array_equal(lone_sightings(statuses), [True, False, False, True, False])
