"""ROS messages as numbers: PointCloud2 records, TF trees and timed poses, voxel-merged sweeps.

The message-level half of :mod:`app.core.formats.rosbag`: it works on deserialised messages
(any object with the ROS field names) and knows nothing of bag files.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from app.core.errors import PointCloudError

if TYPE_CHECKING:  # scipy (0.3 CPU s) is imported when a bag is read, not with the formats
    from scipy.spatial.transform import Rotation

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
class Transform:
    """A rigid transform mapping points of a child frame into its parent frame."""

    rotation: Rotation
    translation: NDArray[np.float64]

    def __mul__(self, other: Transform) -> Transform:
        return Transform(
            self.rotation * other.rotation,
            self.rotation.apply(other.translation) + self.translation,
        )

    def inverse(self) -> Transform:
        inverse_rotation = self.rotation.inv()
        return Transform(inverse_rotation, -inverse_rotation.apply(self.translation))


@cache
def identity() -> Transform:
    """The transform that moves nothing (made once, on first use)."""
    from scipy.spatial.transform import Rotation

    return Transform(Rotation.identity(), np.zeros(3))


class TimedPoses:
    """Poses sampled in time (one TF edge, or a pose topic), interpolated between samples."""

    def __init__(self) -> None:
        self._samples: dict[float, tuple[list[float], list[float]]] = {}

    def add(self, time: float, translation: list[float], quaternion: list[float]) -> None:
        """Record the pose at ``time`` (seconds): translation (3,), quaternion (x, y, z, w)."""
        self._samples[time] = (translation, quaternion)

    def __len__(self) -> int:
        return len(self._samples)

    def freeze(self) -> None:
        """Sort the samples into ``times`` (m,), ``translations`` (m, 3) and ``rotations``;
        call once, after the last :meth:`add` and before :meth:`at`."""
        from scipy.spatial.transform import Rotation, Slerp

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

    def at(self, time: float) -> Transform | None:
        """The pose at ``time``, or None outside the samples' span (plus the tolerance)."""
        if time < self.times[0] - EXTRAPOLATION_SECONDS:
            return None
        if time > self.times[-1] + EXTRAPOLATION_SECONDS:
            return None
        if self._slerp is None:
            return Transform(self.rotations[0], self.translations[0])
        clamped = min(max(time, self.times[0]), self.times[-1])
        index = int(np.clip(np.searchsorted(self.times, clamped), 1, len(self.times) - 1))
        t0, t1 = self.times[index - 1], self.times[index]
        weight = (clamped - t0) / (t1 - t0)
        translation = (1 - weight) * self.translations[index - 1] + weight * self.translations[
            index
        ]
        return Transform(self._slerp([clamped])[0], translation)


class TransformTree:
    """The bag's TF tree: each child frame's parent, with static or timed transforms."""

    def __init__(self) -> None:
        self.parent: dict[str, str] = {}
        self.static: dict[str, Transform] = {}
        self.dynamic: dict[str, TimedPoses] = {}

    def add(self, message: Any, is_static: bool) -> None:
        """Record the transforms of a ``tf2_msgs/TFMessage`` (from ``/tf_static`` when
        ``is_static``); leading slashes of frame names are dropped."""
        from scipy.spatial.transform import Rotation

        for stamped in message.transforms:
            child = frame_name(stamped.child_frame_id)
            parent = frame_name(stamped.header.frame_id)
            if not child or not parent or child == parent:
                continue
            self.parent[child] = parent
            translation = vector_of(stamped.transform.translation)
            quaternion = quaternion_of(stamped.transform.rotation)
            if is_static:
                self.static[child] = Transform(
                    Rotation.from_quat(quaternion), np.array(translation)
                )
            else:
                self.dynamic.setdefault(child, TimedPoses()).add(
                    stamp_seconds(stamped.header.stamp), translation, quaternion
                )

    def freeze(self) -> None:
        """Prepare every timed link for interpolation (after the last :meth:`add`)."""
        for poses in self.dynamic.values():
            poses.freeze()

    @property
    def frames(self) -> list[str]:
        """Every frame named by a transform, sorted."""
        return sorted({*self.parent, *self.parent.values()})

    def root_of(self, frame: str) -> str:
        """The frame at the top of ``frame``'s chain of parents (``frame`` itself if none)."""
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

    def to_root(self, frame: str, time: float) -> Transform | None:
        """Transform from ``frame`` to the root of its tree at ``time``; None when a timed link
        has no pose near ``time``."""
        transform = identity()
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

    def lookup(self, target: str, source: str, time: float) -> Transform | None:
        """Transform from ``source`` into ``target`` (same tree) at ``time``, or None."""
        source_to_root = self.to_root(source, time)
        target_to_root = self.to_root(target, time)
        if source_to_root is None or target_to_root is None:
            return None
        return target_to_root.inverse() * source_to_root


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
        an offset from the stamp or an absolute time (see :func:`point_times`).
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


def point_times(stamp: float, offsets: NDArray[np.float64] | None, n: int) -> NDArray:
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


class VoxelMap:
    """Points merged a chunk of sweeps at a time, keeping the newest point of each voxel."""

    def __init__(self, voxel_size: float) -> None:
        self.voxel_size = voxel_size
        self.points = np.empty((0, 3))
        self.times = np.empty(0)
        self._pending: list[tuple[NDArray, NDArray]] = []
        self._pending_count = 0
        self._origin: NDArray[np.int64] | None = None

    def add(self, points: NDArray[np.float64], times: NDArray[np.float64]) -> None:
        """Queue one placed sweep: ``points`` (n, 3) and their ``times`` (n,), newer than
        everything queued before."""
        self._pending.append((points, times))
        self._pending_count += len(points)
        if self._pending_count >= CHUNK_POINTS:
            self._merge()

    def holds_at_most(self, limit: int) -> bool:
        """Whether the merged map has at most ``limit`` points (merges the pending sweeps only
        when their raw count passes the limit)."""
        if len(self.points) + self._pending_count > limit:
            self._merge()
        return len(self.points) <= limit

    def result(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The merged map: points (n, 3) and times (n,), in the order they were added."""
        self._merge()
        return self.points, self.times

    def _merge(self) -> None:
        if not self._pending:
            return
        points = np.concatenate([self.points, *(p for p, _ in self._pending)])
        times = np.concatenate([self.times, *(t for _, t in self._pending)])
        self._pending, self._pending_count = [], 0
        if self.voxel_size > 0 and len(points):
            newest = newest_per_voxel(self._keys(points))
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


def newest_per_voxel(keys: NDArray[np.int64]) -> NDArray[np.int64]:
    """Rows (ascending) of the last row of each distinct key."""
    _, first_in_reversed = np.unique(keys[::-1], return_index=True)
    return np.sort(len(keys) - 1 - first_in_reversed)


def frame_name(name: str) -> str:
    return name.lstrip("/")


def stamp_seconds(stamp: Any) -> float:
    return float(stamp.sec) + float(stamp.nanosec) * 1e-9


def vector_of(value: Any) -> list[float]:
    return [float(value.x), float(value.y), float(value.z)]


def quaternion_of(value: Any) -> list[float]:
    return [float(value.x), float(value.y), float(value.z), float(value.w)]
