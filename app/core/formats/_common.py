"""Plumbing shared by the format readers: the input buffer, limits and error helpers.

Every reader receives a :class:`Source` (the whole content as a read-only buffer, memory-mapped
for files so binary bodies are decoded without an extra copy) and returns a :class:`RawCloud`
(coordinates that may still contain NaN rows, plus attributes); :func:`read_point_cloud` turns it
into a validated :class:`~app.core.cloud.PointCloud`.
"""

from __future__ import annotations

import io
import mmap
import os
import re
from collections.abc import Iterator, Mapping
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import numpy as np
from numpy.typing import NDArray

from app.core.blocks import FileRows
from app.core.errors import PointCloudError, PointLimitError
from app.core.trajectory import Trajectory

SourceLike = str | os.PathLike | bytes | bytearray | memoryview | BinaryIO


@dataclass
class Source:
    """The complete content of one input, plus what is known about where it came from.

    Attributes
    ----------
    buffer : bytes-like
        The whole content, read-only (an ``mmap`` for files, the bytes themselves otherwise).
    path : Path or None
        The file, when the input was a path (libraries that want a file object open it).
    name : str or None
        A file name for messages and suffix-based detection.
    file_descriptor : int or None
        The open file behind a memory-mapped ``buffer`` (valid while the source is open).
    """

    buffer: bytes | memoryview | mmap.mmap
    path: Path | None = None
    name: str | None = None
    file_descriptor: int | None = None

    @property
    def size(self) -> int:
        """Number of bytes of content."""
        return len(self.buffer)

    def head(self, n_bytes: int) -> bytes:
        """The first ``n_bytes`` bytes (fewer when the content is shorter)."""
        return bytes(self.buffer[:n_bytes])

    def stream(self) -> BinaryIO:
        """A seekable binary stream over the content (a new file handle for paths)."""
        if self.path is not None:
            return open(self.path, "rb")
        return io.BytesIO(bytes(self.buffer))

    def as_bytes(self) -> bytes:
        """The content as ``bytes`` (a copy for memory-mapped files)."""
        if isinstance(self.buffer, bytes):
            return self.buffer
        return bytes(self.buffer)


@dataclass
class RawCloud:
    """What a reader decoded, before :meth:`PointCloud.from_array` validates it.

    Attributes
    ----------
    points : ndarray, shape (n, 3), any real dtype
        Coordinates in file order; may contain non-finite rows. Binary readers give a read-only
        view of the input buffer (e.g. float32 records, see :func:`xyz_points`):
        :meth:`PointCloud.from_array` converts it to an owned float64 array in one pass, so the
        view never outlives the buffer.
    attributes : dict of str to ndarray, each shape (n, ...)
        Extra per-point fields, owned arrays (never views of the input buffer).
    sensor_origin : ndarray, shape (3,), or None
    trajectory : Trajectory or None
        The moving sensor's path (a ROS bag's poses at its sweep stamps).
    """

    points: NDArray[np.float64]
    attributes: dict[str, NDArray] = field(default_factory=dict)
    sensor_origin: NDArray[np.float64] | None = None
    trajectory: Trajectory | None = None


@contextmanager
def open_source(source: SourceLike, filename: str | None = None) -> Iterator[Source]:
    """Expose ``source`` (path, bytes or binary file object) as a :class:`Source`.

    Files are memory-mapped read-only (an empty file gives an empty buffer); file objects are
    read from their current position to the end.

    Raises
    ------
    PointCloudError
        The path does not exist, is a directory or cannot be read.
    """
    if isinstance(source, str | os.PathLike):
        path = Path(source)
        try:
            handle = open(path, "rb")  # noqa: SIM115 - closed below
        except FileNotFoundError as exc:
            raise PointCloudError(f"file not found: {path}") from exc
        except IsADirectoryError as exc:
            raise PointCloudError(f"{path} is a directory, not a point-cloud file") from exc
        except PermissionError as exc:
            raise PointCloudError(f"permission denied reading {path}") from exc
        with handle:
            size = os.fstat(handle.fileno()).st_size
            if size == 0:
                yield Source(b"", path, filename or path.name)
                return
            mapped = mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ)
            try:
                yield Source(mapped, path, filename or path.name, handle.fileno())
            finally:
                # An array view of the map may still be referenced (e.g. by a traceback);
                # the map is then released when that view is garbage-collected.
                with suppress(BufferError):
                    mapped.close()
        return
    if isinstance(source, bytes | bytearray | memoryview):
        yield Source(memoryview(source).toreadonly(), None, filename)
        return
    if hasattr(source, "read"):
        content = source.read()
        if isinstance(content, str):
            raise PointCloudError(
                "the file object is open in text mode; open it in binary mode ('rb')"
            )
        name = filename or _stream_name(source)
        yield Source(bytes(content), None, name)
        return
    raise PointCloudError(
        f"cannot read a point cloud from a {type(source).__name__}; "
        "give a path, bytes or a binary file object"
    )


def _stream_name(stream: object) -> str | None:
    name = getattr(stream, "name", None)
    if isinstance(name, str) and name and not name.startswith("<"):
        return os.path.basename(name)
    return None


def check_point_count(
    declared: int,
    max_points: int | None,
    what: str,
    *,
    available_bytes: int | None = None,
    bytes_per_point: int | None = None,
) -> None:
    """Refuse a declared point count before anything is allocated for it.

    Parameters
    ----------
    declared : int
        Points the header claims.
    max_points : int or None
        The caller's limit (None: no limit).
    what : str
        Where the count comes from, for the message (e.g. "the PLY header").
    available_bytes, bytes_per_point : int, optional
        When both are given, also refuse counts the body is too short to hold (truncation).

    Raises
    ------
    PointCloudError
        Negative count, more than ``max_points``, or a body too short for the count.
    """
    if declared < 0:
        raise PointCloudError(f"{what} declares a negative point count ({declared})")
    if max_points is not None and declared > max_points:
        raise PointLimitError(
            f"{what} declares {declared:,} points, more than the limit of {max_points:,}; "
            "split or downsample the scan, or raise the limit",
            limit_name="max_points",
        )
    if available_bytes is not None and bytes_per_point:
        needed = declared * bytes_per_point
        if needed > available_bytes:
            held = available_bytes // bytes_per_point
            raise PointCloudError(
                f"truncated body: {what} declares {declared:,} points "
                f"({needed:,} bytes) but only {available_bytes:,} bytes follow the header "
                f"(room for {held:,} points); the file was cut short: upload it again"
            )


def owned(array: NDArray) -> NDArray:
    """A native-byte-order array that owns its memory (never a view of the input buffer)."""
    array = np.asarray(array)
    dtype = array.dtype
    if dtype.byteorder not in ("=", "|") and dtype.byteorder != _NATIVE:
        dtype = dtype.newbyteorder("=")
    return np.array(array, dtype=dtype, copy=True, order="C")


_NATIVE = "<" if np.little_endian else ">"


def xyz_from_columns(x: NDArray, y: NDArray, z: NDArray) -> NDArray[np.float64]:
    """Stack three coordinate columns (any numeric dtype, any strides) into (n, 3) float64.

    Returns
    -------
    ndarray, shape (n, 3), float64, C-contiguous
    """
    view = xyz_view(x, y, z)
    if view is not None:
        with np.errstate(invalid="ignore"):  # signalling NaNs: see below
            return view.astype(np.float64, order="C")
    points = np.empty((len(x), 3), dtype=np.float64)
    # Signalling NaNs in float32 data raise the "invalid" flag when widened: they are NaN rows
    # like any other (dropped and counted later), not an error.
    with np.errstate(invalid="ignore"):
        points[:, 0] = x
        points[:, 1] = y
        points[:, 2] = z
    return points


def xyz_view(x: NDArray, y: NDArray, z: NDArray) -> NDArray | None:
    """The three coordinate columns as one (n, 3) view, without copying, when the layout allows.

    That is when they are 1-D views of the same buffer with the same dtype and stride, and y
    and z follow x at equal distances: ``x y z`` side by side in each record of a PLY/PCD body
    (packed or padded), or three consecutive column blocks (a compressed PCD body).

    Returns
    -------
    ndarray, shape (n, 3), or None
        A read-only view of the buffer; None when the layout differs.
    """
    columns = (x, y, z)
    if not all(isinstance(c, np.ndarray) and c.ndim == 1 for c in columns):
        return None
    base = x.base
    if (
        base is None
        or not all(c.base is base for c in columns)
        or not (x.dtype == y.dtype == z.dtype)
        or not (x.strides == y.strides == z.strides)
        or not (len(x) == len(y) == len(z))
        or x.dtype.kind not in "iuf"
    ):
        return None
    address = x.__array_interface__["data"][0]
    step = y.__array_interface__["data"][0] - address
    if step < x.dtype.itemsize or z.__array_interface__["data"][0] - address != 2 * step:
        return None
    # Each column of the view is exactly one of x, y, z: it reads no byte they do not cover.
    return np.lib.stride_tricks.as_strided(
        x, shape=(len(x), 3), strides=(x.strides[0], step), writeable=False
    )


def xyz_points(x: NDArray, y: NDArray, z: NDArray) -> NDArray:
    """The coordinates for a :class:`RawCloud`: :func:`xyz_view` when possible (no copy; the
    float64 conversion then happens once, in :meth:`PointCloud.from_array`), else
    :func:`xyz_from_columns`.

    Returns
    -------
    ndarray, shape (n, 3)
    """
    view = xyz_view(x, y, z)
    return view if view is not None else xyz_from_columns(x, y, z)


def find_xyz_names(names: list[str] | tuple[str, ...], what: str) -> tuple[str, str, str]:
    """Pick the x, y and z field names among ``names`` (exact first, then case-insensitive).

    Raises
    ------
    PointCloudError
        One of x, y, z is missing.
    """
    chosen = []
    for axis in ("x", "y", "z"):
        if axis in names:
            chosen.append(axis)
            continue
        matches = [name for name in names if name.lower() == axis]
        if not matches:
            raise PointCloudError(
                f"{what} has no {axis!r} field (fields: {', '.join(names) or 'none'}); "
                "a point cloud needs x, y and z"
            )
        chosen.append(matches[0])
    return chosen[0], chosen[1], chosen[2]


def file_rows_of(points: NDArray, source: Source) -> FileRows | None:
    """Where ``points``, an (n, 3) view of ``source``'s memory map, lies in its file; else None.

    :meth:`PointCloud.from_array` then reads it block by block with ``pread`` instead of
    through the map (see :class:`~app.core.blocks.FileRows`).
    """
    if source.file_descriptor is None or not isinstance(source.buffer, mmap.mmap):
        return None
    if (
        not isinstance(points, np.ndarray)
        or points.ndim != 2
        or points.shape[0] == 0
        or points.shape[1] != 3
        or points.dtype.kind not in "iuf"
        or points.strides[0] <= 0
        or points.strides[1] <= 0
    ):
        return None
    mapped = np.frombuffer(source.buffer, dtype=np.uint8)
    try:
        start = points.__array_interface__["data"][0] - mapped.__array_interface__["data"][0]
        row_stride, step = points.strides
        end = start + (points.shape[0] - 1) * row_stride + 2 * step + points.dtype.itemsize
        inside = 0 <= start and end <= mapped.size
    finally:
        del mapped  # the map can be closed again
    return FileRows(source.file_descriptor, start) if inside else None


def has_nonzero_bytes(buffer: bytes | memoryview | mmap.mmap, start: int) -> bool:
    """Whether ``buffer[start:]`` holds anything but zero bytes (padding)."""
    return bool(np.frombuffer(buffer, dtype=np.uint8, offset=start).any())


def ascii_body(source: Source, offset: int, not_ascii: str) -> str:
    """The bytes of ``source`` from ``offset`` on, decoded as ASCII text.

    Parameters
    ----------
    source : Source
    offset : int
        Where the body starts.
    not_ascii : str
        The error message when a byte is not ASCII; ``{offset}`` in it becomes that byte's
        offset in the file.

    Raises
    ------
    PointCloudError
        A byte is not ASCII.
    """
    try:
        return bytes(source.buffer[offset:]).decode("ascii")
    except UnicodeDecodeError as exc:
        raise PointCloudError(not_ascii.format(offset=offset + exc.start)) from exc


def loadtxt_problem(exc: ValueError) -> str:
    """``numpy.loadtxt``'s message with 1-based data-row numbers and without its API hints."""
    message = str(exc).split("; use `usecols`")[0].rstrip(".")
    return re.sub(r"at row (\d+)", lambda match: f"in data row {int(match.group(1)) + 1}", message)


def structured_attributes(
    data: NDArray, skip: tuple[str, ...], rename: Mapping[str, str] | None = None
) -> dict[str, NDArray]:
    """Copy every field of a structured array except ``skip`` into owned attribute arrays."""
    attributes: dict[str, NDArray] = {}
    for name in data.dtype.names or ():
        if name in skip:
            continue
        attributes[(rename or {}).get(name, name)] = owned(data[name])
    return attributes
