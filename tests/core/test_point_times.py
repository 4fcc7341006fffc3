"""Per-point times read from real files place each point's sensor on its trajectory (issue 29).

Rules checked: an E57 file's ``timeStamp`` (written by libE57Format), LAS ``gps_time`` and
PLY/PCD ``time``/``timestamp``/``t`` fields are read as the cloud's per-point times, so that
with the trajectory recorded alongside, every point's sensor position is the trajectory
interpolated at that point's own time (the pseudo-stations are built from times, not from line
of sight); an E57 scan whose times are flagged invalid has no times (line of sight is used).
"""

from __future__ import annotations

import numpy as np
import pytest

from app.core.formats import read_point_cloud
from app.core.trajectory import Trajectory
from app.core.trajectory_poses import interpolate_positions, sensor_groups, with_trajectory
from app.testing.e57_times import e57_with_times_bytes
from app.testing.files import las_bytes, pcd_bytes, ply_bytes

START = 100.0
"""The clock's value when the sensor passes x = 0."""
SPEED = 0.5
"""Metres a second along x."""
SIDE = np.array([-1.5, 1.2])
"""The sensor's (y, z): it drives along x beside the points."""


def corridor_points(count: int = 2000) -> np.ndarray:
    return np.random.default_rng(4).uniform((0.0, 0.0, 0.0), (6.0, 3.0, 2.5), (count, 3))


def time_at(x: np.ndarray) -> np.ndarray:
    """When the sensor was level with x: each point is measured as the sensor passes it."""
    return START + np.asarray(x, dtype=np.float64) / SPEED


def drive() -> Trajectory:
    """The sensor's path: poses every 0.4 s from before the first point to after the last."""
    times = np.arange(START - 1.0, time_at(6.0) + 1.0, 0.4)
    along = (times - START) * SPEED
    positions = np.column_stack([along, np.full_like(along, SIDE[0]), np.full_like(along, 1.2)])
    return Trajectory(times, positions)


def written(kind: str, points: np.ndarray) -> tuple[bytes, str]:
    times = time_at(points[:, 0])
    if kind == "e57 timeStamp":
        return e57_with_times_bytes(points, times), "scan.e57"
    if kind == "las gps_time":
        return las_bytes(points, point_format=1, scale=0.0001, gps_time=times), "scan.las"
    if kind == "pcd time":
        return pcd_bytes(points, extra={"time": times}), "scan.pcd"
    field = kind.split()[1]
    return ply_bytes(points, coordinate_type="f8", extra={field: times}), "scan.ply"


@pytest.mark.parametrize(
    "kind", ["e57 timeStamp", "las gps_time", "ply time", "ply timestamp", "ply t", "pcd time"]
)
def test_each_point_takes_the_trajectory_position_at_its_own_time(kind: str) -> None:
    content, filename = written(kind, corridor_points())

    cloud = with_trajectory(read_point_cloud(content, filename=filename), drive())
    times = cloud.attributes["time"]
    positions, outside = interpolate_positions(cloud.trajectory, times)
    groups = sensor_groups(cloud.points, cloud.trajectory, times, group_length=0.25)

    # the sensor was level with each point when it measured it, whatever order it was read in
    np.testing.assert_allclose(positions[:, 0], cloud.points[:, 0], atol=1e-3)
    np.testing.assert_allclose(positions[:, 1:], np.broadcast_to(SIDE, (len(times), 2)))
    assert not outside.any()
    assert groups.report["assignment"] == "times" and groups.report["points_outside"] == 0
    # each pseudo-station's origin is the mean sensor position of its own points
    for group in np.unique(groups.group)[:: max(1, groups.origins.shape[0] // 6)]:
        members = groups.group == group
        np.testing.assert_allclose(
            groups.origins[group], positions[members].mean(axis=0), atol=1e-6
        )


def test_an_e57_scan_with_invalid_times_falls_back_to_line_of_sight() -> None:
    points = corridor_points(800)
    flagged = np.zeros(len(points), dtype=bool)
    flagged[::50] = True
    content = e57_with_times_bytes(points, time_at(points[:, 0]), time_invalid=flagged)
    valid = e57_with_times_bytes(points, time_at(points[:, 0]), time_invalid=np.zeros_like(flagged))

    cloud = read_point_cloud(content, filename="flagged.e57")
    groups = sensor_groups(cloud.points, drive(), cloud.attributes.get("time"))

    assert "time" not in cloud.attributes
    assert groups.report["assignment"] == "line_of_sight"
    assert "time" in read_point_cloud(valid, filename="valid.e57").attributes
