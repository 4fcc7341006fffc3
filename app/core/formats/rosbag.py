"""ROS bags as scans: the lidar sweeps of a bag, placed by its poses, merged into one map.

A robot records its lidar as ``sensor_msgs/PointCloud2`` messages in the sensor's frame and its
motion as TF (``/tf``, ``/tf_static``) or as an odometry / pose topic. :func:`read_rosbag`
streams the sweeps of one cloud topic, places each in a fixed frame by the pose of its
``header.frame_id`` at its stamp (TF chains interpolated in time, or the pose topic's pose of its
child frame composed with a static TF to the sensor), thins the merged points on a voxel grid a
chunk of sweeps at a time (one point per voxel, the newest, with its time) and returns the map
with the sensor's poses at the sweep stamps as its :class:`~app.core.trajectory.Trajectory` and
each point's time (sweep stamp plus the point's own offset when the message has one) as the
``"time"`` attribute.

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
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation, Slerp

from app.core.errors import PointCloudError
from app.core.formats._common import RawCloud, Source
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
TIME_FIELDS = ("t", "time", "timestamp")
"""PointCloud2 field names read as per-point times (offsets from the stamp, or absolute)."""

EXTRAPOLATION_SECONDS = 0.1
"""A sweep stamped at most this long before the first or after the last pose takes that pose;
sweeps further outside the poses' time span are skipped (and counted in the error if none is
left)."""

CHUNK_POINTS = 1_000_000
"""Raw points gathered from consecutive sweeps before they are merged into the voxel map."""

VOXEL_KEY_BITS = 21
"""Bits per axis of a packed voxel key: the map may span 2**21 voxels (105 km at 5 cm) a side."""

_FLOAT_TYPES = {7: "f4", 8: "f8"}
_POINT_FIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", **_FLOAT_TYPES}


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
    try:
        if "voxel_size" in values:
            parsed["voxel_size"] = float(values["voxel_size"])
        if "max_sweeps" in values:
            parsed["max_sweeps"] = int(values["max_sweeps"])
    except ValueError as exc:
        raise PointCloudError(
            f"bag parameter value is not a number ({exc}): give voxel_size in metres "
            "(e.g. 0.05) and max_sweeps as a whole number"
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


@dataclass(frozen=True)
class _Transform:
    """A rigid transform mapping points of a child frame into its parent frame."""

    rotation: Rotation
    translation: NDArray[np.float64]

    def __mul__(self, other: _Transform) -> _Transform:
        return _Transform(
            self.rotation * other.rotation,
            self.rotation.apply(other.translation) + self.translation,
        )

    def inverse(self) -> _Transform:
        inverse_rotation = self.rotation.inv()
        return _Transform(inverse_rotation, -inverse_rotation.apply(self.translation))


_IDENTITY = _Transform(Rotation.identity(), np.zeros(3))


class _TimedPoses:
    """Poses sampled in time (one TF edge, or a pose topic), interpolated between samples."""

    def __init__(self) -> None:
        self._samples: dict[float, tuple[list[float], list[float]]] = {}

    def add(self, time: float, translation: list[float], quaternion: list[float]) -> None:
        self._samples[time] = (translation, quaternion)

    def __len__(self) -> int:
        return len(self._samples)

    def freeze(self) -> None:
        times = np.array(sorted(self._samples), dtype=np.float64)
        self.times = times
        self.translations = np.array([self._samples[t][0] for t in times], dtype=np.float64)
        quaternions = np.array([self._samples[t][1] for t in times], dtype=np.float64)
        norms = np.linalg.norm(quaternions, axis=1)
        if not (np.isfinite(quaternions).all() and np.isfinite(self.translations).all()):
            raise PointCloudError("the bag holds a pose with non-finite values")
        if (norms < 1e-6).any():
            raise PointCloudError("the bag holds a pose whose quaternion is zero")
        rotations = Rotation.from_quat(quaternions / norms[:, None])
        self.rotations = rotations
        self._slerp = Slerp(times, rotations) if len(times) > 1 else None

    def at(self, time: float) -> _Transform | None:
        """The pose at ``time``, or None outside the samples' span (plus the tolerance)."""
        if time < self.times[0] - EXTRAPOLATION_SECONDS:
            return None
        if time > self.times[-1] + EXTRAPOLATION_SECONDS:
            return None
        if self._slerp is None:
            return _Transform(self.rotations[0], self.translations[0])
        clamped = min(max(time, self.times[0]), self.times[-1])
        index = int(np.clip(np.searchsorted(self.times, clamped), 1, len(self.times) - 1))
        t0, t1 = self.times[index - 1], self.times[index]
        weight = (clamped - t0) / (t1 - t0)
        translation = (1 - weight) * self.translations[index - 1] + weight * self.translations[
            index
        ]
        return _Transform(self._slerp([clamped])[0], translation)


class _TransformTree:
    """The bag's TF tree: each child frame's parent, with static or timed transforms."""

    def __init__(self) -> None:
        self.parent: dict[str, str] = {}
        self.static: dict[str, _Transform] = {}
        self.dynamic: dict[str, _TimedPoses] = {}

    def add(self, message: Any, is_static: bool) -> None:
        for stamped in message.transforms:
            child = _frame(stamped.child_frame_id)
            parent = _frame(stamped.header.frame_id)
            if not child or not parent or child == parent:
                continue
            self.parent[child] = parent
            translation = _vector(stamped.transform.translation)
            quaternion = _quaternion(stamped.transform.rotation)
            if is_static:
                self.static[child] = _Transform(
                    Rotation.from_quat(quaternion), np.array(translation)
                )
            else:
                self.dynamic.setdefault(child, _TimedPoses()).add(
                    _seconds(stamped.header.stamp), translation, quaternion
                )

    def freeze(self) -> None:
        for poses in self.dynamic.values():
            poses.freeze()

    @property
    def frames(self) -> list[str]:
        return sorted({*self.parent, *self.parent.values()})

    def root_of(self, frame: str) -> str:
        seen = {frame}
        while frame in self.parent:
            frame = self.parent[frame]
            if frame in seen:
                raise PointCloudError(f"the bag's TF tree has a cycle through frame {frame!r}")
            seen.add(frame)
        return frame

    def moves(self, frame: str) -> bool:
        """Whether a timed transform lies between ``frame`` and the root of its tree."""
        self.root_of(frame)  # raises on a cycle
        while frame in self.parent:
            if frame not in self.static:
                return True
            frame = self.parent[frame]
        return False

    def to_root(self, frame: str, time: float) -> _Transform | None:
        """Transform from ``frame`` to the root of its tree at ``time``; None when a timed link
        has no pose near ``time``."""
        transform = _IDENTITY
        while frame in self.parent:
            if frame in self.static:
                link = self.static[frame]
            else:
                link = self.dynamic[frame].at(time)
                if link is None:
                    return None
            transform = link * transform
            frame = self.parent[frame]
        return transform

    def lookup(self, target: str, source: str, time: float) -> _Transform | None:
        """Transform from ``source`` into ``target`` (same tree) at ``time``, or None."""
        source_to_root = self.to_root(source, time)
        target_to_root = self.to_root(target, time)
        if source_to_root is None or target_to_root is None:
            return None
        return target_to_root.inverse() * source_to_root


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
        except Exception as exc:
            raise PointCloudError(
                f"cannot open the ROS bag ({type(exc).__name__}: {exc}); the file may be "
                "truncated or corrupt: upload the complete recording (a ROS 1 bag must be "
                "indexed: run 'rosbag reindex' on it)"
            ) from exc
        try:
            return _read_map(reader, options, max_points)
        finally:
            reader.close()


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
    tree = _TransformTree()
    tf_connections = [c for c in connections if c.msgtype in TF_TYPES]
    for connection, _, raw in reader.messages(connections=tf_connections):
        tree.add(
            reader.deserialize(raw, connection.msgtype), connection.topic.lstrip("/") == "tf_static"
        )
    tree.freeze()
    cloud_frame = _first_cloud_frame(reader, cloud_connections)
    locate = _pose_source(reader, connections, tree, cloud_frame, options)
    voxel_map = _VoxelMap(options.voxel_size)
    stamps: list[float] = []
    poses: list[_Transform] = []
    skipped = 0
    for connection, log_time, raw in reader.messages(connections=cloud_connections):
        if options.max_sweeps is not None and len(stamps) >= options.max_sweeps:
            break
        message = reader.deserialize(raw, connection.msgtype)
        stamp = _seconds(message.header.stamp) or log_time * 1e-9
        pose = locate(_frame(message.header.frame_id), stamp)
        if pose is None:
            skipped += 1
            continue
        points, offsets = decode_point_cloud2(message)
        times = _point_times(stamp, offsets, len(points))
        voxel_map.add(pose.rotation.apply(points) + pose.translation, times)
        stamps.append(stamp)
        poses.append(pose)
    if not stamps:
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
    return RawCloud(points, {"time": times}, trajectory=_trajectory(stamps, poses))


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
        return _frame(reader.deserialize(raw, connection.msgtype).header.frame_id)
    raise PointCloudError(f"the topic {cloud_connections[0].topic!r} has no messages")


def _pose_source(
    reader: Any, connections: list[Any], tree: _TransformTree, cloud_frame: str, options: BagOptions
) -> Any:
    """A function ``(frame, stamp) -> transform into the fixed frame or None``."""
    pose_topics = sorted({c.topic for c in connections if c.msgtype in POSE_TYPES})
    topic = options.pose_topic
    if topic is not None and topic not in pose_topics:
        raise PointCloudError(
            f"pose_topic {topic!r} is not an odometry or pose topic of the bag; its pose "
            f"topics: {', '.join(pose_topics) or 'none'}"
        )
    if topic is None and cloud_frame in tree.parent:
        # TF places the sweeps when it moves them (or nothing else could): a static chain up
        # to the robot's body leaves the motion to the pose topic
        if tree.moves(cloud_frame) or not pose_topics or options.fixed_frame is not None:
            return _tf_source(tree, cloud_frame, options.fixed_frame)
    if topic is None and options.fixed_frame is not None and cloud_frame != options.fixed_frame:
        raise PointCloudError(
            f"fixed_frame {options.fixed_frame!r} is not linked by TF to the cloud's frame "
            f"{cloud_frame!r}; frames in the bag's TF: {', '.join(tree.frames) or 'none'}"
        )
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
    poses = _TimedPoses()
    child_frames: set[str] = set()
    for connection, log_time, raw in reader.messages(
        connections=[c for c in connections if c.topic == topic]
    ):
        message = reader.deserialize(raw, connection.msgtype)
        pose = message.pose.pose if hasattr(message.pose, "pose") else message.pose
        poses.add(
            _seconds(message.header.stamp) or log_time * 1e-9,
            _vector(pose.position),
            _quaternion(pose.orientation),
        )
        child_frames.add(_frame(getattr(message, "child_frame_id", "")))
    if not len(poses):
        raise PointCloudError(f"the pose topic {topic!r} has no messages")
    poses.freeze()
    child = child_frames.pop() if len(child_frames) == 1 else ""

    def locate(frame: str, stamp: float) -> _Transform | None:
        body_pose = poses.at(stamp)
        if body_pose is None:
            return None
        if child and frame != child and tree.root_of(frame) == tree.root_of(child):
            mount = tree.lookup(child, frame, stamp)
            return None if mount is None else body_pose * mount
        return body_pose

    return locate


def _tf_source(tree: _TransformTree, cloud_frame: str, fixed_frame: str | None) -> Any:
    root = tree.root_of(cloud_frame)
    if fixed_frame is None:
        fixed_frame = root
    elif fixed_frame not in tree.parent and fixed_frame != root:
        raise PointCloudError(
            f"fixed_frame {fixed_frame!r} is not linked by TF to the cloud's frame "
            f"{cloud_frame!r}; frames linked to it: "
            f"{', '.join(f for f in tree.frames if tree.root_of(f) == root)}"
        )

    def locate(frame: str, stamp: float) -> _Transform | None:
        if frame not in tree.parent or tree.root_of(frame) != tree.root_of(fixed_frame):
            return None
        return tree.lookup(fixed_frame, frame, stamp)

    return locate


def decode_point_cloud2(
    message: Any,
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """The finite points of a ``sensor_msgs/PointCloud2`` and their time field, if any.

    Parameters
    ----------
    message : PointCloud2
        A deserialised message: ``x``, ``y``, ``z`` fields of type float32 or float64 at any
        offsets of a ``point_step`` record (padding allowed), rows of ``row_step`` bytes, either
        byte order.

    Returns
    -------
    points : ndarray, shape (n, 3), float64
        In the message's frame; points with a non-finite coordinate, and points at exactly the
        origin (no return), are dropped.
    times : ndarray, shape (n,), float64, or None
        The ``t``/``time``/``timestamp`` field in seconds (integers are read as nanoseconds):
        an offset from the stamp or an absolute time (see :func:`_point_times`).
    """
    fields = {field.name: field for field in message.fields}
    missing = [name for name in "xyz" if name not in fields]
    if missing:
        raise PointCloudError(
            f"a PointCloud2 message has no {', '.join(missing)} field (fields: "
            f"{', '.join(fields)}); the cloud topic must hold x, y, z points"
        )
    order = ">" if message.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for name in "xyz":
        field = fields[name]
        if field.datatype not in _FLOAT_TYPES:
            raise PointCloudError(
                f"PointCloud2 field {name!r} has datatype {field.datatype}; x, y, z must be "
                "float32 (7) or float64 (8)"
            )
        names.append(name)
        formats.append(order + _FLOAT_TYPES[field.datatype])
        offsets.append(field.offset)
    time_name = next((name for name in TIME_FIELDS if name in fields), None)
    if time_name is not None and fields[time_name].datatype in _POINT_FIELD_TYPES:
        names.append("time")
        formats.append(order + _POINT_FIELD_TYPES[fields[time_name].datatype])
        offsets.append(fields[time_name].offset)
    else:
        time_name = None
    width, height, step = int(message.width), int(message.height), int(message.point_step)
    row_step = int(message.row_step) or width * step
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    data = np.asarray(message.data, dtype=np.uint8)
    if step < dtype.itemsize or row_step < width * step or data.size < row_step * height:
        raise PointCloudError(
            f"a PointCloud2 message is inconsistent: {height} rows of {width} points of "
            f"{step} bytes (row_step {row_step}) need more than its {data.size} data bytes"
        )
    rows = data[: row_step * height].reshape(height, row_step)[:, : width * step]
    records = np.ascontiguousarray(rows).view(dtype).reshape(-1)
    points = np.column_stack([records[n].astype(np.float64) for n in "xyz"])
    keep = np.isfinite(points).all(axis=1) & (points != 0).any(axis=1)
    times = None
    if time_name is not None:
        times = records["time"].astype(np.float64)[keep]
        if records.dtype["time"].kind in "iu":
            times *= 1e-9
    return points[keep], times


def _point_times(stamp: float, offsets: NDArray[np.float64] | None, n: int) -> NDArray:
    """Absolute times: the stamp, plus per-point offsets; values beyond 1e6 s are absolute
    already (floats beyond 1e12 are nanoseconds)."""
    if offsets is None or offsets.size == 0:
        return np.full(n, stamp)
    largest = float(np.abs(offsets).max())
    if largest > 1e12:
        return offsets * 1e-9
    if largest > 1e6:
        return offsets
    return stamp + offsets


class _VoxelMap:
    """Points merged a chunk of sweeps at a time, keeping the newest point of each voxel."""

    def __init__(self, voxel_size: float) -> None:
        self.voxel_size = voxel_size
        self.points = np.empty((0, 3))
        self.times = np.empty(0)
        self._pending: list[tuple[NDArray, NDArray]] = []
        self._pending_count = 0
        self._origin: NDArray[np.int64] | None = None

    def add(self, points: NDArray[np.float64], times: NDArray[np.float64]) -> None:
        self._pending.append((points, times))
        self._pending_count += len(points)
        if self._pending_count >= CHUNK_POINTS:
            self._merge()

    def result(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        self._merge()
        return self.points, self.times

    def _merge(self) -> None:
        if not self._pending:
            return
        points = np.concatenate([self.points, *(p for p, _ in self._pending)])
        times = np.concatenate([self.times, *(t for _, t in self._pending)])
        self._pending, self._pending_count = [], 0
        if self.voxel_size > 0 and len(points):
            newest = _newest_per_voxel(self._keys(points))
            points, times = points[newest], times[newest]
        self.points, self.times = points, times

    def _keys(self, points: NDArray[np.float64]) -> NDArray[np.int64]:
        cells = np.floor(points / self.voxel_size).astype(np.int64)
        if self._origin is None:
            self._origin = cells[0] - (1 << (VOXEL_KEY_BITS - 1))
        cells -= self._origin
        if cells.min() < 0 or cells.max() >= 1 << VOXEL_KEY_BITS:
            raise PointCloudError(
                f"the bag's map spans more than {1 << VOXEL_KEY_BITS} voxels of "
                f"{self.voxel_size} m along an axis; set a larger voxel_size"
            )
        return (cells[:, 0] << (2 * VOXEL_KEY_BITS)) | (cells[:, 1] << VOXEL_KEY_BITS) | cells[:, 2]


def _newest_per_voxel(keys: NDArray[np.int64]) -> NDArray[np.int64]:
    """Rows (ascending) of the last row of each distinct key."""
    _, first_in_reversed = np.unique(keys[::-1], return_index=True)
    return np.sort(len(keys) - 1 - first_in_reversed)


def _trajectory(stamps: list[float], poses: list[_Transform]) -> Trajectory:
    times, first = np.unique(np.array(stamps), return_index=True)
    positions = np.array([poses[i].translation for i in first])
    orientations = np.array([poses[i].rotation.as_quat() for i in first])
    return Trajectory(times, positions, orientations)


def _frame(name: str) -> str:
    return name.lstrip("/")


def _seconds(stamp: Any) -> float:
    return float(stamp.sec) + float(stamp.nanosec) * 1e-9


def _vector(value: Any) -> list[float]:
    return [float(value.x), float(value.y), float(value.z)]


def _quaternion(value: Any) -> list[float]:
    return [float(value.x), float(value.y), float(value.z), float(value.w)]
