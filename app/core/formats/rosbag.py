"""ROS bags as scans: the lidar sweeps of a bag, placed by its poses, merged into one map.

A robot records its lidar as ``sensor_msgs/PointCloud2`` messages in the sensor's frame and its
motion as TF (``/tf``, ``/tf_static``) or as an odometry / pose topic. :func:`read_rosbag`
streams the sweeps of one cloud topic, places each in a fixed frame by the pose of its
``header.frame_id`` at its stamp (TF chains interpolated in time, or the pose topic's pose of its
child frame composed with a static TF to the sensor), thins the merged points on a voxel grid a
chunk of sweeps at a time (one point per voxel, the newest, with its time) and returns the map
with the sensor's poses at the sweep stamps as its :class:`~app.core.trajectory.Trajectory` and
each point's time (sweep stamp plus the point's own offset when the message has one) as the
``"time"`` attribute. Sweeps recorded in the pose topic's frame already (a SLAM's registered
clouds) are kept in place, with the pose topic's poses as the trajectory; sweeps in the root
frame of TF with no pose topic are kept in place without a trajectory.

Formats (all read with the pure-Python ``rosbags`` package): ROS 1 ``.bag`` (message
definitions embedded), ROS 2 ``.mcap`` (schemas embedded) and a bare ROS 2 ``.db3`` SQLite
storage file (definitions embedded by recent recorders; otherwise the ROS 2 Humble types are
used). Topics and frames are chosen automatically when there is one obvious choice; otherwise
the error names the candidates and the :class:`BagOptions` field to set.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from app.core.errors import PointCloudError
from app.core.formats._common import RawCloud, Source
from app.core.formats.ros_messages import (
    TimedPoses,
    Transform,
    TransformTree,
    VoxelMap,
    decode_point_cloud2,
    frame_name,
    identity,
    point_times,
    quaternion_of,
    stamp_seconds,
    vector_of,
)
from app.core.trajectory import Trajectory

BAG_FORMATS: tuple[str, ...] = ("bag", "db3", "mcap")
"""File suffixes of ROS bags: ROS 1 bags, ROS 2 SQLite storage files, ROS 2 MCAP files."""

ROS1_MAGIC = b"#ROSBAG V2.0"
SQLITE_MAGIC = b"SQLite format 3\x00"
MCAP_MAGIC = b"\x89MCAP0\r\n"

CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")
POSE_TYPES = (
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
)


@dataclass(frozen=True)
class BagOptions:
    """How to read a ROS bag; every field is chosen automatically when left as None.

    Attributes
    ----------
    cloud_topic : str or None
        The ``sensor_msgs/PointCloud2`` topic whose sweeps make the map (default: the bag's
        only one).
    fixed_frame : str or None
        The TF frame the map is built in (default: the root of the TF tree above the cloud's
        frame, e.g. ``map``, ``odom`` or ``world``).
    pose_topic : str or None
        A ``nav_msgs/Odometry``, ``geometry_msgs/PoseStamped`` or
        ``geometry_msgs/PoseWithCovarianceStamped`` topic placing the sweeps instead of TF
        (default: TF when it links the cloud's frame to a fixed frame, else the bag's only
        pose topic).
    voxel_size : float
        Edge of the voxel grid thinning the map, metres; one point (the newest) is kept per
        voxel. 0 keeps every point.
    max_sweeps : int or None
        Read at most this many sweeps (default: all).
    """

    cloud_topic: str | None = None
    fixed_frame: str | None = None
    pose_topic: str | None = None
    voxel_size: float = 0.05
    max_sweeps: int | None = None

    def __post_init__(self) -> None:
        if not np.isfinite(self.voxel_size) or self.voxel_size < 0:
            raise PointCloudError(
                f"voxel_size must be a finite number of metres >= 0, got {self.voxel_size!r}"
            )
        if self.max_sweeps is not None and self.max_sweeps < 1:
            raise PointCloudError(f"max_sweeps must be at least 1, got {self.max_sweeps!r}")


def bag_options_from_strings(values: dict[str, str]) -> BagOptions:
    """Build :class:`BagOptions` from ``KEY=VALUE`` strings (CLI flags, form fields).

    Raises
    ------
    PointCloudError
        An unknown key or a value that is not a number where one is needed.
    """
    known = ("cloud_topic", "fixed_frame", "pose_topic", "voxel_size", "max_sweeps")
    unknown = sorted(set(values) - set(known))
    if unknown:
        raise PointCloudError(
            f"unknown bag parameter(s) {', '.join(unknown)}; known: {', '.join(known)}"
        )
    parsed: dict[str, Any] = {k: v for k, v in values.items() if k in known[:3]}
    for key, number, what in (
        ("voxel_size", float, "a number of metres (e.g. 0.05)"),
        ("max_sweeps", int, "a whole number"),
    ):
        if key in values:
            try:
                parsed[key] = number(values[key])
            except ValueError as exc:
                raise PointCloudError(
                    f"bag parameter {key} is {values[key]!r}, not a number: give {what}"
                ) from exc
    return BagOptions(**parsed)


def sniff_bag(head: bytes) -> str | None:
    """``bag``, ``db3`` or ``mcap`` when the first bytes are those of a ROS bag, else None."""
    if head.startswith(ROS1_MAGIC):
        return "bag"
    if head.startswith(MCAP_MAGIC):
        return "mcap"
    if head.startswith(SQLITE_MAGIC):
        return "db3"
    return None


def read_rosbag(
    source: Source, max_points: int | None, kind: str, options: BagOptions | None = None
) -> RawCloud:
    """Read the map of a ROS bag: placed, voxel-thinned sweeps with their trajectory.

    Parameters
    ----------
    source : Source
        The bag's content (a path when it came from a file).
    max_points : int or None
        Refuse a map with more points than this.
    kind : str
        ``bag``, ``db3`` or ``mcap`` (one of :data:`BAG_FORMATS`).
    options : BagOptions, optional
        Topics, frames and voxel size (default: chosen automatically, 5 cm voxels).

    Returns
    -------
    RawCloud
        ``points`` (n, 3) float64 in the fixed frame; ``attributes["time"]`` (n,) float64
        seconds; ``trajectory`` with the sensor's poses (xyzw quaternions) at the sweep stamps.

    Raises
    ------
    PointCloudError
        The bag is corrupt or truncated, has no point clouds or no poses, or the choice of
        topic or frame is ambiguous (the message names the candidates and the option to set).
    """
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    options = options or BagOptions()
    with _bag_path(source, kind) as path:
        try:
            reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
            reader.open()
            try:
                return _read_map(reader, options, max_points)
            finally:
                reader.close()
        except (PointCloudError, MemoryError, AttributeError, NameError, AssertionError):
            raise
        except Exception as exc:  # rosbags' reader, storage and deserialisation errors
            reason = str(exc).replace(str(path), "the file")  # no temporary paths in messages
            hint = " (a ROS 1 bag must be indexed: run 'rosbag reindex' on it)" * (kind == "bag")
            raise PointCloudError(
                f"cannot read the ROS bag ({type(exc).__name__}: {reason}); the file may be "
                f"truncated or corrupt: upload the complete recording{hint}"
            ) from exc


@contextmanager
def _bag_path(source: Source, kind: str) -> Iterator[Path]:
    """A path to the bag whose suffix is ``.kind`` (rosbags chooses its reader by suffix)."""
    if source.path is not None and source.path.suffix == f".{kind}":
        yield source.path
        return
    with tempfile.TemporaryDirectory(prefix="scandiff-bag-") as directory:
        path = Path(directory) / f"recording.{kind}"
        if source.path is not None:
            os.symlink(source.path.resolve(), path)
        else:
            path.write_bytes(source.as_bytes())
        yield path


def _read_map(reader: Any, options: BagOptions, max_points: int | None) -> RawCloud:
    connections = reader.connections
    cloud_connections = _cloud_connections(connections, options.cloud_topic)
    tree = TransformTree()
    tf_connections = [c for c in connections if c.msgtype in TF_TYPES]
    # an empty connection list would mean every message: read TF only when there is some
    for connection, _, raw in reader.messages(connections=tf_connections) if tf_connections else ():
        tree.add(
            reader.deserialize(raw, connection.msgtype), connection.topic.lstrip("/") == "tf_static"
        )
    tree.freeze()
    cloud_frame = _first_cloud_frame(reader, cloud_connections)
    locate = _pose_source(reader, connections, tree, cloud_frame, options)
    voxel_map = VoxelMap(options.voxel_size)
    stamps: list[float] = []
    poses: list[Transform] = []
    skipped = n_sweeps = 0
    for connection, log_time, raw in reader.messages(connections=cloud_connections):
        if options.max_sweeps is not None and n_sweeps >= options.max_sweeps:
            break
        message = reader.deserialize(raw, connection.msgtype)
        stamp = stamp_seconds(message.header.stamp) or log_time * 1e-9
        located = locate(frame_name(message.header.frame_id), stamp)
        if located is None:
            skipped += 1
            continue
        placement, sensor_pose = located
        points, offsets = decode_point_cloud2(message)
        times = point_times(stamp, offsets, len(points))
        voxel_map.add(placement.rotation.apply(points) + placement.translation, times)
        n_sweeps += 1
        if max_points is not None and not voxel_map.holds_at_most(max_points):
            raise PointCloudError(
                f"the bag's map passed the limit of {max_points:,} points after "
                f"{n_sweeps} sweeps; set a larger voxel_size or max_sweeps"
            )
        if sensor_pose is not None:
            stamps.append(stamp)
            poses.append(sensor_pose)
    if not n_sweeps:
        raise PointCloudError(
            f"none of the {skipped} sweeps of {cloud_connections[0].topic!r} has a pose at its "
            "stamp: the bag's poses do not cover the sweeps' times; record the poses with the "
            "clouds, or set pose_topic / fixed_frame"
        )
    points, times = voxel_map.result()
    if max_points is not None and len(points) > max_points:
        raise PointCloudError(
            f"the bag's map has {len(points):,} points, more than the limit of {max_points:,}; "
            "set a larger voxel_size"
        )
    trajectory = _trajectory(stamps, poses) if stamps else None
    return RawCloud(points, {"time": times}, trajectory=trajectory)


def _cloud_connections(connections: list[Any], cloud_topic: str | None) -> list[Any]:
    clouds = sorted({c.topic for c in connections if c.msgtype == CLOUD_TYPE})
    if cloud_topic is not None:
        if cloud_topic not in clouds:
            raise PointCloudError(
                f"cloud_topic {cloud_topic!r} is not a sensor_msgs/PointCloud2 topic of the bag; "
                f"its PointCloud2 topics: {', '.join(clouds) or 'none'}"
            )
        chosen = cloud_topic
    elif len(clouds) == 1:
        chosen = clouds[0]
    elif not clouds:
        topics = ", ".join(sorted(f"{c.topic} ({c.msgtype})" for c in connections)) or "none"
        raise PointCloudError(
            f"the bag has no sensor_msgs/PointCloud2 topic (its topics: {topics}): record the "
            "lidar's point clouds in the bag"
        )
    else:
        raise PointCloudError(
            f"the bag has {len(clouds)} sensor_msgs/PointCloud2 topics ({', '.join(clouds)}): "
            "set cloud_topic to the one that makes the map"
        )
    return [c for c in connections if c.topic == chosen and c.msgtype == CLOUD_TYPE]


def _first_cloud_frame(reader: Any, cloud_connections: list[Any]) -> str:
    for connection, _, raw in reader.messages(connections=cloud_connections):
        return frame_name(reader.deserialize(raw, connection.msgtype).header.frame_id)
    raise PointCloudError(f"the topic {cloud_connections[0].topic!r} has no messages")


def _pose_source(
    reader: Any, connections: list[Any], tree: TransformTree, cloud_frame: str, options: BagOptions
) -> Any:
    """A function ``(frame, stamp) -> (placement, sensor pose) or None``.

    ``placement`` takes the sweep's points into the fixed frame; ``sensor pose`` is the
    sensor's pose in that frame, None when unknown (sweeps recorded in the fixed frame already,
    with no pose of the sensor); None for both when the poses do not reach ``stamp``.
    """
    pose_topics = sorted({c.topic for c in connections if c.msgtype in POSE_TYPES})
    topic = options.pose_topic
    if topic is not None and topic not in pose_topics:
        raise PointCloudError(
            f"pose_topic {topic!r} is not an odometry or pose topic of the bag; its pose "
            f"topics: {', '.join(pose_topics) or 'none'}"
        )
    fixed = options.fixed_frame
    fixed_in_tf = (
        fixed is not None
        and cloud_frame in tree.parent
        and fixed in tree.frames
        and tree.root_of(fixed) == tree.root_of(cloud_frame)
    )
    # TF places the sweeps when it moves them, when the fixed frame is one of its frames, or
    # when nothing else could: a static chain up to the robot's body leaves the motion to the
    # pose topic
    if (
        topic is None
        and cloud_frame in tree.parent
        and (tree.moves(cloud_frame) or not pose_topics or fixed_in_tf)
    ):
        return _tf_source(tree, cloud_frame, fixed)
    if (
        topic is None
        and not pose_topics
        and cloud_frame in tree.frames
        and fixed in (None, cloud_frame)
    ):
        return lambda frame, stamp: (identity(), None) if frame == cloud_frame else None
    if topic is None:
        if len(pose_topics) > 1:
            raise PointCloudError(
                f"the cloud's frame {cloud_frame!r} is not in the bag's TF and the bag has "
                f"{len(pose_topics)} pose topics ({', '.join(pose_topics)}): set pose_topic"
            )
        if not pose_topics:
            raise PointCloudError(
                f"the bag has no poses for its sweeps: no /tf transform from the cloud's frame "
                f"{cloud_frame!r} to a fixed frame (TF frames: {', '.join(tree.frames) or 'none'})"
                " and no nav_msgs/Odometry or geometry_msgs/PoseStamped topic; record /tf or "
                "odometry with the clouds, or set pose_topic"
            )
        topic = pose_topics[0]
    poses, child_frames, pose_frames = _read_pose_topic(reader, connections, topic)
    if fixed is not None and pose_frames != {fixed}:
        raise PointCloudError(
            f"fixed_frame {fixed!r} is neither linked by TF to the cloud's frame {cloud_frame!r} "
            f"nor the frame of the poses of {topic!r} ({', '.join(sorted(pose_frames))}); "
            "leave fixed_frame unset or name one of these"
        )
    poses.freeze()
    child = child_frames.pop() if len(child_frames) == 1 else ""
    pose_frame = pose_frames.pop() if len(pose_frames) == 1 else None

    def locate(frame: str, stamp: float) -> tuple[Transform, Transform | None] | None:
        body_pose = poses.at(stamp)
        if body_pose is None:
            return None
        if frame == pose_frame:  # registered sweeps (e.g. a SLAM's output): in place already
            return identity(), body_pose
        if child and frame != child and tree.root_of(frame) == tree.root_of(child):
            mount = tree.lookup(child, frame, stamp)
            return None if mount is None else (body_pose * mount, body_pose * mount)
        return body_pose, body_pose

    return locate


def _read_pose_topic(
    reader: Any, connections: list[Any], topic: str
) -> tuple[TimedPoses, set[str], set[str]]:
    """The poses of an odometry or pose topic, the frames they move (``child_frame_id``) and
    the frames they are given in."""
    poses = TimedPoses()
    child_frames: set[str] = set()
    pose_frames: set[str] = set()
    for connection, log_time, raw in reader.messages(
        connections=[c for c in connections if c.topic == topic]
    ):
        message = reader.deserialize(raw, connection.msgtype)
        pose = message.pose.pose if hasattr(message.pose, "pose") else message.pose
        poses.add(
            stamp_seconds(message.header.stamp) or log_time * 1e-9,
            vector_of(pose.position),
            quaternion_of(pose.orientation),
        )
        child_frames.add(frame_name(getattr(message, "child_frame_id", "")))
        pose_frames.add(frame_name(message.header.frame_id))
    if not len(poses):
        raise PointCloudError(f"the pose topic {topic!r} has no messages")
    return poses, child_frames, pose_frames


def _tf_source(tree: TransformTree, cloud_frame: str, fixed_frame: str | None) -> Any:
    root = tree.root_of(cloud_frame)
    if fixed_frame is None:
        fixed_frame = root
    elif fixed_frame not in tree.frames or tree.root_of(fixed_frame) != root:
        raise PointCloudError(
            f"fixed_frame {fixed_frame!r} is not linked by TF to the cloud's frame "
            f"{cloud_frame!r}; frames linked to it: "
            f"{', '.join(f for f in tree.frames if tree.root_of(f) == root)}"
        )

    def locate(frame: str, stamp: float) -> tuple[Transform, Transform] | None:
        if frame not in tree.parent or tree.root_of(frame) != tree.root_of(fixed_frame):
            return None
        pose = tree.lookup(fixed_frame, frame, stamp)
        return None if pose is None else (pose, pose)

    return locate


def _trajectory(stamps: list[float], poses: list[Transform]) -> Trajectory:
    times, first = np.unique(np.array(stamps), return_index=True)
    positions = np.array([poses[i].translation for i in first])
    orientations = np.array([poses[i].rotation.as_quat() for i in first])
    return Trajectory(times, positions, orientations)
