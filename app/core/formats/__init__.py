"""Point-cloud file formats: detection, reading and writing.

One module per format family (:mod:`.ply`, :mod:`.pcd`, :mod:`.las`, :mod:`.e57`, :mod:`.text`,
:mod:`.npy`, :mod:`.rosbag`);
this package chooses the family from the file suffix or, when the suffix is missing, unknown or
contradicted by the content, from the content's magic bytes.

Reading contract: :func:`read_point_cloud` returns a validated :class:`PointCloud` (float64
coordinates, non-finite rows dropped and counted, extra per-point fields as attributes) or raises
:class:`PointCloudError` / :class:`UnsupportedFormatError` whose message starts with the file
name and says what is wrong and how to fix it. No library exception (``KeyError``,
``struct.error``, ``ValueError``, ``MemoryError``, ``UnicodeDecodeError``, ...) escapes. Point
counts declared by headers are checked against ``max_points`` and against the bytes present
before anything is allocated or decompressed. :func:`summarise_point_cloud` makes the same
checks and reports the counts and bounds of that cloud without building it (uploads).

Example
-------
>>> cloud = read_point_cloud("scan.laz")                       # doctest: +SKIP
>>> cloud = read_point_cloud(upload_bytes, filename="scan.ply")  # doctest: +SKIP
>>> write_point_cloud("labels.ply", cloud.points, {"label": labels})  # doctest: +SKIP
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Mapping
from pathlib import PurePath
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from app.core.blocks import conversion_threads
from app.core.cloud import PointCloud
from app.core.cloud_summary import CloudSummary, summarise_array
from app.core.errors import PointCloudError, PointLimitError, UnsupportedFormatError
from app.core.formats import text as _text
from app.core.formats._common import RawCloud, Source, SourceLike, file_rows_of, open_source
from app.core.formats.e57 import E57_SIGNATURE, read_e57
from app.core.formats.las import (
    extra_dimension_names,
    is_compressed_point_format,
    read_las,
    summarise_las,
    write_las,
)
from app.core.formats.npy import read_npy, read_npz
from app.core.formats.pcd import read_pcd
from app.core.formats.ply import read_ply, write_ply
from app.core.formats.rosbag import BAG_FORMATS, BagOptions, read_rosbag, sniff_bag
from app.core.formats.station_fields import has_station_fields, with_station_fields
from app.core.formats.trajectory_files import with_point_times
from app.core.threads import available_threads

SUPPORTED_FORMATS: tuple[str, ...] = (
    "ply",
    "pcd",
    "las",
    "laz",
    "e57",
    "xyz",
    "csv",
    "txt",
    "npy",
    "npz",
    *BAG_FORMATS,
)
"""Formats :func:`read_point_cloud` reads (names are the usual file suffixes)."""

WRITABLE_FORMATS: tuple[str, ...] = ("ply", "las", "laz")
"""Formats :func:`write_point_cloud` writes."""

TEXT_FORMATS: tuple[str, ...] = ("xyz", "csv", "txt")
SNIFF_BYTES = 4096
"""How much of the content :func:`read_point_cloud` shows to :func:`detect_format`."""

Decoded = TypeVar("Decoded")

_READERS: dict[str, Callable[[Source, int | None], RawCloud]] = {
    "ply": read_ply,
    "pcd": read_pcd,
    "las": read_las,
    "laz": read_las,
    "e57": read_e57,
    "xyz": _text.read_text,
    "csv": _text.read_text,
    "txt": _text.read_text,
    "npy": read_npy,
    "npz": read_npz,
}

_PROGRAMMING_ERRORS = (AttributeError, NameError, AssertionError)
"""Never reported as bad input: these are bugs and must surface as such."""


def detect_format(filename: str | None, head: bytes) -> str:
    """Decide the format of a file from its name and its first bytes.

    The suffix decides when it is a supported format and the content does not contradict it
    (content that matches no format leaves the decision to the suffix, so the reader can say
    precisely what is wrong). The content decides when the suffix is missing or unknown, or when
    it clearly is another format (``scan.txt`` holding a binary PLY is read as PLY). ``las`` and
    ``laz`` are told apart by the compression bit of the LAS header's point-format byte.

    Parameters
    ----------
    filename : str or None
        File name or path; only its suffix is used (case-insensitive).
    head : bytes
        The first bytes of the content (a few hundred suffice; 4 KiB makes text detection
        reliable).

    Returns
    -------
    str
        One of :data:`SUPPORTED_FORMATS`.

    Raises
    ------
    UnsupportedFormatError
        Neither the suffix nor the content identifies a supported format.
    """
    suffix = PurePath(filename).suffix.lower().lstrip(".") if filename else ""
    sniffed = sniff_format(head)
    if suffix in SUPPORTED_FORMATS:
        if sniffed is None or sniffed == suffix:
            return suffix
        if suffix in TEXT_FORMATS and sniffed in TEXT_FORMATS:
            return suffix
        return sniffed
    if sniffed is not None:
        return sniffed
    described = f"{filename!r}" if filename else "the content"
    if not head:
        reason = "the content is empty"
    elif suffix:
        reason = f"the suffix '.{suffix}' is not a point-cloud format and the content is not one"
    else:
        reason = "there is no file suffix and the content matches no known format"
    raise UnsupportedFormatError(
        f"cannot tell the point-cloud format of {described}: {reason}; supported formats: "
        f"{', '.join(SUPPORTED_FORMATS)} (give a file with one of these suffixes)"
    )


def sniff_format(head: bytes) -> str | None:
    """The format the content's first bytes identify, or None.

    Magic bytes: ``ply`` + newline (PLY), ``# .PCD`` or a first header line ``VERSION``/``FIELDS``
    (PCD), ``LASF`` (LAS/LAZ), ``ASTM-E57`` (E57), ``\\x93NUMPY`` (NPY), ``PK\\x03\\x04`` (NPZ, a
    zip archive), ``#ROSBAG V2.0`` (ROS 1 bag), ``SQLite format 3`` (ROS 2 ``.db3``),
    ``\\x89MCAP0`` (ROS 2 ``.mcap``);
    otherwise UTF-8 text whose first data row has at least three numbers is ``csv`` when
    comma-separated and ``xyz`` otherwise.
    """
    if head.startswith(b"ply") and head[3:4] in (b"\n", b"\r"):
        return "ply"
    if head.startswith(b"LASF"):
        if len(head) > 104 and is_compressed_point_format(head[104]):
            return "laz"
        return "las"
    if head.startswith(E57_SIGNATURE):
        return "e57"
    if head.startswith(b"\x93NUMPY"):
        return "npy"
    if head.startswith((b"PK\x03\x04", b"PK\x05\x06")):
        return "npz"
    if (bag := sniff_bag(head)) is not None:
        return bag
    if _looks_like_pcd(head):
        return "pcd"
    return _sniff_text(head)


def _looks_like_pcd(head: bytes) -> bool:
    """A PCD header: '# .PCD' or a first non-comment line starting VERSION or FIELDS.

    Works on bytes: a binary PCD body (NUL bytes, anything) may follow the header in ``head``.
    """
    if head.lstrip().startswith(b"# .PCD"):
        return True
    for line in head.split(b"\n", 32)[:32]:
        stripped = line.strip()
        if not stripped or stripped.startswith(b"#"):
            continue
        return stripped.split(None, 1)[0].upper() in (b"VERSION", b"FIELDS")
    return False


def _sniff_text(head: bytes) -> str | None:
    if b"\x00" in head:
        return None
    try:
        text = head.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        if exc.start < len(head) - 3:
            return None
        text = head[: exc.start].decode("utf-8-sig")  # a character cut by the head's end
    lines = text.splitlines()
    if len(lines) > 1 and not text.endswith(("\n", "\r")):
        lines = lines[:-1]  # the last line may be cut by the head's end
    _, first_data = _text._find_header(lines)
    if first_data is None:
        return None
    row = lines[first_data].strip()
    delimiter, decimal_comma = _text._detect_delimiter(row)
    values = _text._split(row, delimiter)
    if decimal_comma:
        values = [value.replace(",", ".") for value in values]
    if sum(map(_text._is_number, values)) < 3:
        return None
    return "csv" if delimiter == "," else "xyz"


def read_point_cloud(
    source: SourceLike,
    format: str | None = None,
    *,
    filename: str | None = None,
    max_points: int | None = 200_000_000,
    threads: int | None = None,
    bag_options: BagOptions | None = None,
) -> PointCloud:
    """Read a point cloud from a path, bytes or a binary file object.

    Parameters
    ----------
    source : str, os.PathLike, bytes or binary file object
        Files are memory-mapped; file objects are read from their current position.
    format : str, optional
        One of :data:`SUPPORTED_FORMATS` (a leading dot and upper case are accepted). Default:
        :func:`detect_format` from ``filename`` (or the path's name) and the content.
    filename : str, optional
        Name used for detection and messages when ``source`` is bytes or a file object.
    max_points : int or None
        Refuse files whose header declares more points (None: no limit). Checked before any
        allocation or decompression.
    threads : int, optional
        Threads that may decode a large file: they widen binary PLY/PCD coordinates to float64
        and decompress LAZ. Default: for the widening
        :func:`~app.core.blocks.conversion_threads` (``OMP_NUM_THREADS``, else two while the
        load average leaves a CPU idle, else one: Python threads stall each other on a busy
        machine), for LAZ :func:`~app.core.threads.available_threads` (lazrs's decoder threads
        do not hold the GIL and paid off at every load measured but the highest). The cloud
        does not depend on it.
    bag_options : BagOptions, optional
        Topics, frames and voxel size for a ROS bag (``bag``, ``db3``, ``mcap``); default:
        chosen automatically (:mod:`app.core.formats.rosbag`).

    Returns
    -------
    PointCloud
        ``points`` (n, 3) float64; ``attributes`` holds the file's other per-point fields;
        ``sensor_origin`` comes from a PCD ``VIEWPOINT`` when it is not the default one, from
        an E57 file's scan poses ((k, 3) for k scans) or from per-point origin fields; a
        ``station_index`` attribute says which station took each point (E57 scans, per-point
        fields: :mod:`app.core.formats.station_fields`); a ROS bag's map has a ``trajectory`` and a
        ``"time"`` attribute.

    Raises
    ------
    PointCloudError
        Anything wrong with the content; the message starts with the file name.
    UnsupportedFormatError
        The format is unknown or cannot be detected.
    """

    def build(raw: RawCloud, opened: Source) -> PointCloud:
        raw = with_station_fields(raw)
        cloud = PointCloud.from_array(
            raw.points,
            with_point_times(raw.attributes),  # times under "time", whatever the field's name
            raw.sensor_origin,
            threads=conversion_threads() if threads is None else threads,
            file_rows=file_rows_of(raw.points, opened),
        )
        if raw.trajectory is not None:
            cloud = dataclasses.replace(cloud, trajectory=raw.trajectory)
        return cloud

    def build_las(opened: Source, max_points: int | None, threads: int) -> PointCloud:
        return build(read_las(opened, max_points, threads=threads), opened)

    return _decode(source, format, filename, max_points, threads, build, build_las, bag_options)


def summarise_point_cloud(
    source: SourceLike,
    format: str | None = None,
    *,
    filename: str | None = None,
    max_points: int | None = 200_000_000,
    threads: int | None = None,
    bag_options: BagOptions | None = None,
) -> CloudSummary:
    """Check a point cloud as :func:`read_point_cloud` does and summarise it, without loading it.

    For accepting uploads: the same detection, the same checks and the same errors, and the
    counts, bounds and sensor origin of the cloud :func:`read_point_cloud` would return, but
    the coordinates are visited a cache-sized block at a time in the file's own type
    (:func:`~app.core.cloud_summary.summarise_array`), so no float64 copy of the coordinates is
    made: for a binary PLY/PCD the coordinates cost one block of memory whatever the cloud's
    size (extra fields are still copied out, as for reading), for a LAS/LAZ one chunk of
    decoded points (:func:`~app.core.formats.las.summarise_las`), for text a chunk of lines
    (:func:`~app.core.formats.text.summarise_text`), for a ``.npy`` one block (its coordinates
    are a view of the file, as a binary PLY's). An ``.npz`` is decoded as for reading, then
    summarised.

    Parameters
    ----------
    source, format, filename, max_points, threads, bag_options
        As for :func:`read_point_cloud` (``threads`` share the blocks of a binary PLY/PCD,
        or decompress a LAZ; a ROS bag's map is built as for reading, then summarised).

    Returns
    -------
    CloudSummary
        ``n_points``, ``n_dropped``, ``low``/``high`` bounds and ``sensor_origin`` equal to
        those of the cloud :func:`read_point_cloud` returns.

    Raises
    ------
    PointCloudError, UnsupportedFormatError
        As :func:`read_point_cloud`.
    """

    def build(raw: RawCloud, opened: Source) -> CloudSummary:
        raw = with_station_fields(raw)
        return summarise_array(
            raw.points,
            raw.attributes,
            raw.sensor_origin,
            file_rows=file_rows_of(raw.points, opened),
            threads=threads,
        )

    def build_las(opened: Source, max_points: int | None, threads: int) -> CloudSummary:
        # station fields: decoded whole, to count the stations
        if has_station_fields(extra_dimension_names(opened, max_points)):
            return build(read_las(opened, max_points, threads=threads), opened)
        return summarise_las(opened, max_points, threads=threads)

    def build_text(opened: Source, max_points: int | None) -> CloudSummary:
        summary = _text.summarise_text(opened, max_points)
        # station fields: decoded whole, to count the stations
        return build(_text.read_text(opened, max_points), opened) if summary is None else summary

    return _decode(
        source, format, filename, max_points, threads, build, build_las, bag_options, build_text
    )


def _decode(
    source: SourceLike,
    format: str | None,
    filename: str | None,
    max_points: int | None,
    threads: int | None,
    build: Callable[[RawCloud, Source], Decoded],
    build_las: Callable[[Source, int | None, int], Decoded],
    bag_options: BagOptions | None = None,
    build_text: Callable[[Source, int | None], Decoded] | None = None,
) -> Decoded:
    """Open ``source``, choose its format, decode it and hand the raw cloud to ``build``
    (LAS/LAZ go to ``build_las`` with the decoder's thread count, text to ``build_text`` when
    given); every error becomes a :class:`PointCloudError` whose message starts with the file
    name."""
    with open_source(source, filename) as opened:
        label = opened.name or "input"
        chosen = "unknown"
        try:
            chosen = _normalise_format(format) if format else None
            if opened.size == 0:
                raise PointCloudError("the file is empty (0 bytes): zero points")
            if chosen is None:
                chosen = detect_format(opened.name, opened.head(SNIFF_BYTES))
            if chosen in BAG_FORMATS:
                return build(read_rosbag(opened, max_points, chosen, bag_options), opened)
            reader = _READERS[chosen]
            if reader is read_las:
                laz_threads = available_threads() if threads is None else threads
                return build_las(opened, max_points, laz_threads)
            if reader is _text.read_text and build_text is not None:
                return build_text(opened, max_points)
            return build(reader(opened, max_points), opened)
        except PointLimitError as exc:
            raise PointLimitError(f"{label}: {exc}", limit_name=exc.limit_name) from exc
        except PointCloudError as exc:
            raise type(exc)(f"{label}: {exc}") from exc
        except MemoryError as exc:
            raise PointCloudError(
                f"{label}: not enough memory to load this {chosen} file; downsample or split "
                "the scan"
            ) from exc
        except _PROGRAMMING_ERRORS:
            raise
        except Exception as exc:  # any other library error means the content is malformed
            raise PointCloudError(
                f"{label}: malformed {chosen} file ({type(exc).__name__}: {exc})"
            ) from exc


def write_point_cloud(
    path: str | os.PathLike,
    points: NDArray[np.float64],
    fields: Mapping[str, NDArray] | None = None,
    format: str | None = None,
) -> None:
    """Write points and per-point fields to PLY (binary little endian), LAS or LAZ.

    The file appears atomically (written to a temporary name, then renamed).

    Parameters
    ----------
    path : str or os.PathLike
    points : ndarray, shape (n, 3)
        Coordinates; PLY stores float64, LAS/LAZ integers at 0.1 mm resolution (coarser only
        beyond a 214 km extent).
    fields : mapping of str to ndarray, each shape (n,), optional
        Extra per-point values kept with their type, e.g. ``label`` int8, ``distance`` float32,
        ``region`` int32: extra PLY vertex properties, or LAS extra-bytes dimensions.
    format : str, optional
        ``ply``, ``las`` or ``laz``; default from the path's suffix.

    Raises
    ------
    UnsupportedFormatError
        The format is not writable.
    PointCloudError
        Wrong shapes, a field type the format cannot hold, NaN coordinates for LAS.
    """
    target = os.fspath(path)
    chosen = (format or PurePath(target).suffix).lower().lstrip(".")
    if chosen not in WRITABLE_FORMATS:
        raise UnsupportedFormatError(
            f"cannot write {chosen!r} files; writable formats: {', '.join(WRITABLE_FORMATS)}"
        )
    array = np.asarray(points, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 3:
        raise PointCloudError(f"points must have shape (n, 3), got {array.shape}")
    checked_fields: dict[str, NDArray] = {}
    for name, values in (fields or {}).items():
        values = np.asarray(values)
        if values.shape != (len(array),):
            raise PointCloudError(
                f"field {name!r} has shape {values.shape}, expected ({len(array)},): one value "
                "per point"
            )
        checked_fields[name] = values
    if chosen == "ply":
        write_ply(target, array, checked_fields)
    else:
        write_las(target, array, checked_fields, compress=chosen == "laz")


def _normalise_format(format: str) -> str:
    name = format.lower().lstrip(".")
    if name not in SUPPORTED_FORMATS:
        raise UnsupportedFormatError(
            f"unknown point-cloud format {format!r}; supported formats: "
            f"{', '.join(SUPPORTED_FORMATS)}"
        )
    return name


__all__ = [
    "BAG_FORMATS",
    "SUPPORTED_FORMATS",
    "WRITABLE_FORMATS",
    "BagOptions",
    "detect_format",
    "read_point_cloud",
    "sniff_format",
    "summarise_point_cloud",
    "write_point_cloud",
]
