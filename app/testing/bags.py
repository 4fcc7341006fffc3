"""Small ROS bags written with rosbags' writers: a 16-ring lidar swept along a path in a box room.

The lidar rides on ``base_link`` (a static TF ``base_link -> lidar``, turned 90 degrees about
z and raised); the robot's poses are TF ``odom -> base_link`` under a static ``map -> odom``, or
a ``nav_msgs/Odometry`` topic. Sweeps are stamped between pose samples, so the reader must
interpolate. Each sweep is cast in the true world and written in the lidar's frame.
"""

from __future__ import annotations

import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from scipy.spatial.transform import Rotation

from app.core.datasets.lidar import LidarWorld, lidar_directions

SHELL_LOW = np.array([0.0, 0.0, 0.0])
SHELL_HIGH = np.array([8.0, 6.0, 3.0])
BOX_LOW = np.array([[5.0, 1.0, 0.0]])
BOX_HIGH = np.array([[6.0, 2.0, 1.0]])
MAP_TO_ODOM = np.array([0.5, -0.25, 0.0])
MOUNT_TRANSLATION = np.array([0.1, 0.0, 0.4])
MOUNT_ROTATION = Rotation.from_euler("z", 90, degrees=True)
POSE_PERIOD = 0.5
START_TIME = 1_700_000_000.0
NOISE = 0.005


@dataclass(frozen=True)
class WrittenBag:
    """A bag file and what it holds (``world`` and sensor poses in the map's fixed frame)."""

    path: Path
    world: LidarWorld
    sweep_times: NDArray[np.float64]
    sensor_positions: NDArray[np.float64]
    sensor_orientations: NDArray[np.float64]
    n_raw_points: int


def room_world(with_box: bool = True) -> LidarWorld:
    """The room the sweeps see (map frame), with its 1 m box or without it."""
    if not with_box:
        return LidarWorld(SHELL_LOW, SHELL_HIGH, np.empty((0, 3)), np.empty((0, 3)))
    return LidarWorld(SHELL_LOW, SHELL_HIGH, BOX_LOW, BOX_HIGH)


def _base_pose(time: float) -> tuple[NDArray, Rotation]:
    """Robot pose in ``odom`` at ``time`` (linear motion, constant yaw rate)."""
    elapsed = time - START_TIME
    position = np.array([1.5 + 0.8 * elapsed, 2.5 + 0.3 * elapsed, 0.5]) - MAP_TO_ODOM
    return position, Rotation.from_euler("z", 20 * elapsed, degrees=True)


def _sensor_pose(time: float) -> tuple[NDArray, Rotation]:
    """Lidar pose in ``map`` at ``time``."""
    position, rotation = _base_pose(time)
    return MAP_TO_ODOM + position + rotation.apply(MOUNT_TRANSLATION), rotation * MOUNT_ROTATION


def write_lidar_bag(
    directory: Path,
    storage: str,
    *,
    poses: str = "tf",
    n_sweeps: int = 8,
    extra_cloud_topic: bool = False,
    extra_pose_topic: bool = False,
    with_clouds: bool = True,
    with_box: bool = True,
    registered: bool = False,
    seed: int = 0,
    period: float = POSE_PERIOD,
    azimuth_step_deg: float = 4.0,
) -> WrittenBag:
    """Write a bag (``storage``: ``bag``, ``db3`` or ``mcap``) of ``n_sweeps`` lidar sweeps.

    ``poses``: ``"tf"`` (``/tf`` + ``/tf_static``), ``"odometry"`` (``/odom`` +
    ``/tf_static``) or ``"none"`` (no poses at all). The ROS 2 storages are written as a bag
    directory and the bare storage file is returned (no ``metadata.yaml`` beside it), as an
    upload would be. ``registered``: sweeps written in the fixed frame (``odom`` with
    odometry poses, else ``map``) instead of the lidar's. ``period``: seconds between pose
    samples and between sweeps (the robot moves 0.8 m/s: keep ``n_sweeps * period`` under 7 s
    to stay in the room).
    """
    rng = np.random.default_rng(seed)
    world = room_world(with_box)
    directions = lidar_directions(7.0, azimuth_step_deg)  # 16 rings, 90 columns by default
    offsets = np.linspace(0.0, 0.09, len(directions), dtype=np.float32)
    sweep_times = START_TIME + period * (np.arange(n_sweeps) + 0.5)
    pose_times = START_TIME + period * np.arange(n_sweeps + 1)
    is_ros1 = storage == "bag"
    typestore = get_typestore(Stores.ROS1_NOETIC if is_ros1 else Stores.ROS2_HUMBLE)
    if is_ros1:
        typestore.register(
            get_types_from_msg(
                "geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"
            )
        )
    types = typestore.types
    messages: list[tuple[str, str, float, object]] = []

    def header(time: float, frame: str) -> object:
        stamp = types["builtin_interfaces/msg/Time"](sec=int(time), nanosec=round(time % 1 * 1e9))
        if is_ros1:
            return types["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)
        return types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def transform(time: float, parent: str, child: str, position: NDArray, rotation: Rotation):
        vector = types["geometry_msgs/msg/Vector3"](*map(float, position))
        quaternion = types["geometry_msgs/msg/Quaternion"](*map(float, rotation.as_quat()))
        return types["geometry_msgs/msg/TransformStamped"](
            header(time, parent), child, types["geometry_msgs/msg/Transform"](vector, quaternion)
        )

    tf_type = "tf2_msgs/msg/TFMessage"
    static = [
        transform(START_TIME, "map", "odom", MAP_TO_ODOM, Rotation.identity()),
        transform(START_TIME, "base_link", "lidar", MOUNT_TRANSLATION, MOUNT_ROTATION),
    ]
    if poses == "odometry":
        static = static[1:]
    if poses != "none":
        messages.append(("/tf_static", tf_type, START_TIME, types[tf_type](static)))
    for time in pose_times if poses != "none" else ():
        position, rotation = _base_pose(time)
        if poses == "tf":
            stamped = transform(time, "odom", "base_link", position, rotation)
            messages.append(("/tf", tf_type, time, types[tf_type]([stamped])))
        else:
            messages.append(("/odom", *_odometry(types, header(time, "odom"), position, rotation)))
            if extra_pose_topic:
                messages.append(
                    ("/odom_raw", *_odometry(types, header(time, "odom"), position, rotation))
                )
    positions, orientations, n_raw = [], [], 0
    for time in sweep_times:
        position, rotation = _sensor_pose(time)
        distance, _ = world.cast(position, rotation.apply(directions))
        if poses == "odometry":  # the map is built in odom
            position = position - MAP_TO_ODOM
        distance = distance + rng.normal(0, NOISE, distance.shape)
        local = directions * distance[:, None]
        local[rng.random(len(local)) < 0.05] = np.nan  # no returns
        n_raw += int(np.isfinite(local).all(axis=1).sum())
        frame_id = "lidar"
        if registered:  # sweeps in the fixed frame already, as a SLAM publishes them
            frame_id = "odom" if poses == "odometry" else "map"
            local = rotation.apply(local) + position
        message = _point_cloud(types, header(time, frame_id), local, offsets)
        if with_clouds:
            messages.append(("/velodyne_points", "sensor_msgs/msg/PointCloud2", time, message))
        if extra_cloud_topic:
            messages.append(("/front/points", "sensor_msgs/msg/PointCloud2", time, message))
        positions.append(position)
        orientations.append(rotation.as_quat())
    path = _write(directory, storage, typestore, messages)
    if poses == "odometry":
        world = LidarWorld(
            world.shell_low - MAP_TO_ODOM,
            world.shell_high - MAP_TO_ODOM,
            world.box_low - MAP_TO_ODOM,
            world.box_high - MAP_TO_ODOM,
        )
    return WrittenBag(path, world, sweep_times, np.array(positions), np.array(orientations), n_raw)


def _odometry(types: dict, head: object, position: NDArray, rotation: Rotation) -> tuple:
    pose = types["geometry_msgs/msg/Pose"](
        types["geometry_msgs/msg/Point"](*map(float, position)),
        types["geometry_msgs/msg/Quaternion"](*map(float, rotation.as_quat())),
    )
    zero = types["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0)
    message = types["nav_msgs/msg/Odometry"](
        head,
        "base_link",
        types["geometry_msgs/msg/PoseWithCovariance"](pose, np.zeros(36)),
        types["geometry_msgs/msg/TwistWithCovariance"](
            types["geometry_msgs/msg/Twist"](zero, zero), np.zeros(36)
        ),
    )
    stamp = head.stamp  # type: ignore[attr-defined]
    return "nav_msgs/msg/Odometry", stamp.sec + stamp.nanosec * 1e-9, message


def _point_cloud(types: dict, head: object, local: NDArray, offsets: NDArray) -> object:
    """A PointCloud2 with x, y, z float32, a padding gap, intensity and a float32 ``t``."""
    dtype = np.dtype(
        {
            "names": ["x", "y", "z", "intensity", "t"],
            "formats": ["<f4", "<f4", "<f4", "<f4", "<f4"],
            "offsets": [0, 4, 8, 16, 20],
            "itemsize": 32,
        }
    )
    records = np.zeros(len(local), dtype=dtype)
    for index, name in enumerate("xyz"):
        records[name] = local[:, index]
    records["intensity"] = 100.0
    records["t"] = offsets
    field = types["sensor_msgs/msg/PointField"]
    fields = [
        field(name=name, offset=offset, datatype=7, count=1)
        for name, offset in (("x", 0), ("y", 4), ("z", 8), ("intensity", 16), ("t", 20))
    ]
    return types["sensor_msgs/msg/PointCloud2"](
        header=head,
        height=1,
        width=len(records),
        fields=fields,
        is_bigendian=False,
        point_step=32,
        row_step=32 * len(records),
        data=np.frombuffer(records.tobytes(), dtype=np.uint8),
        is_dense=False,
    )


def _write(directory: Path, storage: str, typestore, messages: list) -> Path:
    messages = sorted(messages, key=lambda item: item[2])
    if storage == "bag":
        from rosbags.rosbag1 import Writer as Writer1

        path = directory / "recording.bag"
        with Writer1(path) as writer:
            connections = {}
            for topic, msgtype, time, message in messages:
                if topic not in connections:
                    connections[topic] = writer.add_connection(topic, msgtype, typestore=typestore)
                data = typestore.serialize_ros1(message, msgtype)
                writer.write(connections[topic], int(time * 1e9), data)
        return path
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    plugin = StoragePlugin.SQLITE3 if storage == "db3" else StoragePlugin.MCAP
    with tempfile.TemporaryDirectory(dir=directory) as scratch:
        bag_directory = Path(scratch) / "bag"
        with Writer2(bag_directory, version=9, storage_plugin=plugin) as writer:
            connections = {}
            for topic, msgtype, time, message in messages:
                if topic not in connections:
                    connections[topic] = writer.add_connection(topic, msgtype, typestore=typestore)
                data = typestore.serialize_cdr(message, msgtype)
                writer.write(connections[topic], int(time * 1e9), data)
        (stored,) = bag_directory.glob(f"*.{storage}")
        path = directory / f"recording.{storage}"
        shutil.move(stored, path)
    return path
