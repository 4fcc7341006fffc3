"""ROS bags read as scans (:mod:`app.core.formats.rosbag`).

Rules checked, on small bags written in the test with rosbags' own writers (ROS 1 ``.bag``,
bare ROS 2 ``.db3`` and ``.mcap`` storage files: a 16-ring lidar swept along a path through a
box room, placed by TF or by an odometry topic with a static mount TF):

* the map lies on the room's surfaces (within the range noise), in the fixed frame;
* the trajectory is the lidar's poses at the sweep stamps (interpolated between TF samples);
  every point's ``"time"`` is its sweep's stamp plus its own offset;
* the voxel grid keeps one point per voxel (0 keeps every point);
* format found from the content when the name does not say it; the upload summary agrees
  with the cloud;
* topics and frames are chosen when there is one choice; otherwise, and when clouds or poses
  are missing or the bag is truncated, a PointCloudError names what to set or fix;
* PointCloud2 layouts: big-endian float64 coordinates, row padding, integer nanosecond offsets.
"""

from __future__ import annotations

import sqlite3
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from app.core.errors import PointCloudError
from app.core.formats import (
    BagOptions,
    detect_format,
    read_point_cloud,
    summarise_point_cloud,
)
from app.core.formats.ros_messages import decode_point_cloud2
from app.core.formats.rosbag import bag_options_from_strings
from app.testing.bags import MAP_TO_ODOM, MOUNT_TRANSLATION, NOISE, WrittenBag, write_lidar_bag
from tests.helpers.clouds import assert_summary_of

STORAGES = ("bag", "db3", "mcap")


def _bag(tmp_path: Path, storage: str, **kwargs: object) -> WrittenBag:
    return write_lidar_bag(tmp_path, storage, **kwargs)  # type: ignore[arg-type]


@pytest.mark.parametrize("storage", STORAGES)
@pytest.mark.parametrize("poses", ["tf", "odometry"])
def test_sweeps_placed_by_poses_make_the_map_and_the_trajectory(
    tmp_path: Path, storage: str, poses: str
) -> None:
    written = _bag(tmp_path, storage, poses=poses)
    cloud = read_point_cloud(written.path)

    distance = written.world.surface_distance(cloud.points)
    assert distance.max() < 5 * NOISE
    assert len(cloud) > 0.8 * written.n_raw_points  # 5 cm voxels thin little of 8 sweeps
    trajectory = cloud.trajectory
    assert trajectory is not None
    np.testing.assert_allclose(trajectory.times, written.sweep_times, atol=1e-6)
    np.testing.assert_allclose(trajectory.positions, written.sensor_positions, atol=1e-6)
    same_rotation = np.abs((trajectory.orientations * written.sensor_orientations).sum(axis=1))
    np.testing.assert_allclose(same_rotation, 1.0, atol=1e-9)
    # each point's time: its sweep's stamp plus an offset of 0-0.09 s
    times = cloud.attributes["time"]
    sweep = np.searchsorted(written.sweep_times, times + 1e-6) - 1
    offsets = times - written.sweep_times[sweep]
    assert sweep.min() == 0 and sweep.max() == len(written.sweep_times) - 1
    assert offsets.min() >= -1e-6 and offsets.max() <= 0.09 + 1e-6
    assert np.unique(np.round(offsets, 4)).size > 100


def test_voxel_grid_keeps_one_point_per_voxel(tmp_path: Path) -> None:
    written = _bag(tmp_path, "mcap")
    everything = read_point_cloud(written.path, bag_options=BagOptions(voxel_size=0.0))
    coarse = read_point_cloud(written.path, bag_options=BagOptions(voxel_size=0.3))

    assert len(everything) == written.n_raw_points
    voxels = np.floor(coarse.points / 0.3).astype(np.int64)
    assert len(np.unique(voxels, axis=0)) == len(coarse)
    occupied = np.unique(np.floor(everything.points / 0.3).astype(np.int64), axis=0)
    assert len(coarse) == len(occupied) < len(everything) / 3


def test_max_sweeps_and_fixed_frame(tmp_path: Path) -> None:
    written = _bag(tmp_path, "bag")
    options = BagOptions(fixed_frame="odom", max_sweeps=3)
    cloud = read_point_cloud(written.path, bag_options=options)

    assert cloud.trajectory is not None and len(cloud.trajectory) == 3
    np.testing.assert_allclose(
        cloud.trajectory.positions, written.sensor_positions[:3] - MAP_TO_ODOM, atol=1e-6
    )
    shifted = written.world.surface_distance(cloud.points + MAP_TO_ODOM)
    assert shifted.max() < 5 * NOISE
    with pytest.raises(PointCloudError, match=r"fixed_frame 'earth' is not linked.*map, odom"):
        read_point_cloud(written.path, bag_options=BagOptions(fixed_frame="earth"))


@pytest.mark.parametrize("poses", ["odometry", "tf"])
def test_registered_sweeps_stay_in_place(tmp_path: Path, poses: str) -> None:
    """Sweeps already in the poses' frame (a SLAM's output) are not moved again; the odometry
    poses (of the robot's body, not the lidar) are the trajectory; with TF alone there is none."""
    written = _bag(tmp_path, "mcap", poses=poses, registered=True, n_sweeps=4)
    cloud = read_point_cloud(written.path)

    assert written.world.surface_distance(cloud.points).max() < 5 * NOISE
    if poses == "tf":
        assert cloud.trajectory is None
        return
    assert cloud.trajectory is not None
    np.testing.assert_allclose(cloud.trajectory.times, written.sweep_times, atol=1e-6)
    offsets = np.linalg.norm(cloud.trajectory.positions - written.sensor_positions, axis=1)
    np.testing.assert_allclose(offsets, np.linalg.norm(MOUNT_TRANSLATION), atol=1e-6)


@pytest.mark.parametrize("storage", STORAGES)
def test_format_found_from_content_and_summary_agrees(tmp_path: Path, storage: str) -> None:
    written = _bag(tmp_path, storage, n_sweeps=3)
    content = written.path.read_bytes()

    assert detect_format(None, content[:4096]) == storage
    assert detect_format("robot.dat", content[:4096]) == storage
    from_path = read_point_cloud(written.path)
    from_bytes = read_point_cloud(content, filename="upload")
    np.testing.assert_array_equal(from_bytes.points, from_path.points)
    assert from_bytes.trajectory is not None
    assert_summary_of(summarise_point_cloud(content, filename="upload"), from_path)


def test_several_cloud_topics_need_cloud_topic(tmp_path: Path) -> None:
    written = _bag(tmp_path, "db3", n_sweeps=3, extra_cloud_topic=True)

    with pytest.raises(PointCloudError, match="cloud_topic") as raised:
        read_point_cloud(written.path)
    assert "/front/points" in str(raised.value) and "/velodyne_points" in str(raised.value)
    chosen = read_point_cloud(written.path, bag_options=BagOptions(cloud_topic="/front/points"))
    assert chosen.trajectory is not None and len(chosen.trajectory) == 3
    with pytest.raises(PointCloudError, match="'/nope' is not a sensor_msgs/PointCloud2"):
        read_point_cloud(written.path, bag_options=BagOptions(cloud_topic="/nope"))


def test_several_pose_topics_need_pose_topic(tmp_path: Path) -> None:
    written = _bag(tmp_path, "mcap", poses="odometry", n_sweeps=3, extra_pose_topic=True)

    with pytest.raises(PointCloudError, match="set pose_topic") as raised:
        read_point_cloud(written.path)
    assert "/odom, /odom_raw" in str(raised.value)
    chosen = read_point_cloud(written.path, bag_options=BagOptions(pose_topic="/odom_raw"))
    assert chosen.trajectory is not None
    np.testing.assert_allclose(chosen.trajectory.positions, written.sensor_positions, atol=1e-6)


def test_missing_clouds_or_poses_are_named(tmp_path: Path) -> None:
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    no_clouds = _bag(tmp_path / "a", "bag", n_sweeps=2, with_clouds=False)
    no_poses = _bag(tmp_path / "b", "bag", n_sweeps=2, poses="none")

    with pytest.raises(PointCloudError, match=r"no sensor_msgs/PointCloud2 topic.*/tf"):
        read_point_cloud(no_clouds.path)
    with pytest.raises(PointCloudError, match=r"no poses for its sweeps.*'lidar'.*pose_topic"):
        read_point_cloud(no_poses.path)


@pytest.mark.parametrize("storage", STORAGES)
def test_truncated_bag_is_refused(tmp_path: Path, storage: str) -> None:
    written = _bag(tmp_path, storage, n_sweeps=3)
    content = written.path.read_bytes()

    with pytest.raises(PointCloudError, match="upload"):
        read_point_cloud(content[: len(content) // 2], filename=f"cut.{storage}")
    with pytest.raises(PointCloudError):
        summarise_point_cloud(content[:200], filename=f"cut.{storage}")


def test_bag_options_from_strings() -> None:
    options = bag_options_from_strings({"cloud_topic": "/points", "voxel_size": "0.1"})
    assert options == BagOptions(cloud_topic="/points", voxel_size=0.1)
    with pytest.raises(PointCloudError, match=r"unknown bag parameter.*voxel"):
        bag_options_from_strings({"voxel": "0.1"})
    with pytest.raises(PointCloudError, match="voxel_size"):
        bag_options_from_strings({"voxel_size": "fine"})
    with pytest.raises(PointCloudError, match="voxel_size"):
        bag_options_from_strings({"voxel_size": "-1"})


def test_point_cloud2_layouts() -> None:
    """Big-endian float64 coordinates with padding and row padding; uint32 ns offsets."""
    rng = np.random.default_rng(3)
    points = rng.uniform(-5, 5, (2, 3, 3))
    points[0, 1] = np.nan
    points[1, 2] = 0.0  # no return
    dtype = np.dtype(
        {
            "names": ["x", "y", "z", "t"],
            "formats": [">f8", ">f8", ">f8", ">u4"],
            "offsets": [0, 8, 16, 28],
            "itemsize": 36,
        }
    )
    records = np.zeros((2, 3), dtype=dtype)
    for index, name in enumerate("xyz"):
        records[name] = points[..., index]
    records["t"] = [[0, 10_000_000, 20_000_000], [30_000_000, 40_000_000, 50_000_000]]
    rows = [row.tobytes() + b"\x00" * 4 for row in records]  # row_step = 3 * 36 + 4
    fields = [
        SimpleNamespace(name=name, offset=offset, datatype=datatype, count=1)
        for name, offset, datatype in (("x", 0, 8), ("y", 8, 8), ("z", 16, 8), ("t", 28, 6))
    ]
    message = SimpleNamespace(
        fields=fields,
        is_bigendian=True,
        width=3,
        height=2,
        point_step=36,
        row_step=112,
        data=np.frombuffer(b"".join(rows), dtype=np.uint8),
    )

    decoded, times = decode_point_cloud2(message)

    kept = [(0, 0), (0, 2), (1, 0), (1, 1)]
    np.testing.assert_array_equal(decoded, np.array([points[i, j] for i, j in kept]))
    np.testing.assert_allclose(times, [0.0, 0.02, 0.03, 0.04])
    message.fields = fields[:2]
    with pytest.raises(PointCloudError, match="no z field"):
        decode_point_cloud2(message)


def test_db3_without_message_definitions_uses_the_ros2_types(tmp_path: Path) -> None:
    """Recorders before ROS 2 Iron store no definitions in the .db3 (schema version 3)."""
    written = _bag(tmp_path, "db3", n_sweeps=3)
    with sqlite3.connect(written.path) as database:
        database.execute("DROP TABLE message_definitions")
        database.execute("UPDATE schema SET schema_version = 3")
    database.close()

    cloud = read_point_cloud(written.path)

    assert written.world.surface_distance(cloud.points).max() < 5 * NOISE
    assert cloud.trajectory is not None and len(cloud.trajectory) == 3


def test_map_larger_than_max_points_is_refused(tmp_path: Path) -> None:
    written = _bag(tmp_path, "bag", n_sweeps=3)

    with pytest.raises(PointCloudError, match=r"limit of 1,000 points.*voxel_size"):
        read_point_cloud(written.path, max_points=1000)
