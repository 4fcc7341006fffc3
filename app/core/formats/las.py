"""LAS and LAZ (ASPRS lidar format), read and written with ``laspy`` (LAZ through ``lazrs``).

Coordinates are the *scaled* values ``X * scale + offset`` computed in float64, so georeferenced
data (UTM x ~ 5e5, y ~ 5e6) keeps the file's full resolution (typically 0.1-1 mm).

Kept as attributes: ``intensity``, ``classification``, ``return_number``,
``number_of_returns``, ``gps_time``, ``red``/``green``/``blue``/``nir`` when the point format
has them, and every extra-bytes dimension (e.g. the ``label``/``distance``/``region`` fields
written by :func:`write_las`).

Before any point is decompressed the header's point count is checked against ``max_points``
and against the bytes present: an uncompressed body must hold ``count x record size`` bytes,
and a LAZ body may not claim to expand more than :data:`LAZ_MAX_EXPANSION` times, well above
what the most compressible input there is expands to (figures in docs/performance.md).
A COPC file (``.copc.laz``) is a LAZ file too: its octree hierarchy must count the header's
points (:func:`check_copc_hierarchy`; spatial queries in :mod:`app.core.formats.copc`).
Points are then decoded in chunks into preallocated arrays (:func:`read_las`), or summarised
chunk by chunk without keeping them (:func:`summarise_las`, for checking uploads).
"""

from __future__ import annotations

import struct
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.core.cloud_summary import CloudSummary, FiniteBounds
from app.core.errors import PointCloudError
from app.core.files import atomic_output
from app.core.formats._common import RawCloud, Source, check_point_count

LAZ_MAX_EXPANSION = 10_000
"""Largest accepted ratio of declared uncompressed point bytes to LAZ body bytes."""

CHUNK_POINTS = 1_000_000
SUMMARY_CHUNK_POINTS = 1 << 18
"""Points decoded at a time by :func:`summarise_las` (about 11 MB with the laspy record)."""
LASZIP_VLR_RECORD_ID = 22204
LAS_MIN_HEADER_BYTES = 227
LAS_VLR_HEADER_BYTES = 54
LAZ_MAX_CHUNK_POINTS = 10_000_000
"""Largest fixed LAZ chunk accepted (LASzip writes 50,000)."""
KEPT_STANDARD_DIMENSIONS = (
    "intensity",
    "classification",
    "return_number",
    "number_of_returns",
    "gps_time",
    "red",
    "green",
    "blue",
    "nir",
)
WRITE_POINT_FORMAT = 6
"""LAS 1.4 point format 6: the modern base format (no colour); extra fields go to extra bytes."""


COPC_INFO_VLR_OFFSET = 375
"""Where the ``copc`` info VLR starts: right after the LAS 1.4 header, as COPC requires."""
VLR_HEADER_BYTES = 54
COPC_USER_ID = b"copc"
COPC_INFO_RECORD_ID = 1
COPC_INFO_BYTES = 160
HIERARCHY_ENTRY = struct.Struct("<4iQii")
"""One hierarchy page entry: key (depth, x, y, z), chunk offset, chunk bytes, point count."""
CHILD_PAGE = -1
"""Point count of an entry that references a child hierarchy page."""
POINT_COUNT_OFFSET = 247
"""Byte offset of the LAS 1.4 header's 64-bit point count."""


def is_copc(buffer: bytes | memoryview) -> bool:
    """Whether the LAS/LAZ content starts like a COPC file (its first VLR is ``copc`` info).

    Parameters
    ----------
    buffer : bytes-like
        The file's content, or at least its first 431 bytes.
    """
    start = COPC_INFO_VLR_OFFSET
    if len(buffer) < start + VLR_HEADER_BYTES or bytes(buffer[:4]) != b"LASF":
        return False
    user_id = bytes(buffer[start + 2 : start + 18]).rstrip(b"\0")
    record_id = struct.unpack_from("<H", buffer, start + 18)[0]
    return user_id == COPC_USER_ID and record_id == COPC_INFO_RECORD_ID


def check_copc_hierarchy(source: Source, n_points: int) -> None:
    """Verify the octree hierarchy of a COPC file against its header before decoding it.

    Parameters
    ----------
    source : Source
        The whole file (memory-mapped).
    n_points : int
        The point count the header declares.

    Raises
    ------
    PointCloudError
        A hierarchy page or chunk outside the file, a page visited twice (a cycle), or node
        point counts whose sum differs from the header's count.
    """
    buffer = source.buffer
    info_start = COPC_INFO_VLR_OFFSET + VLR_HEADER_BYTES
    if source.size < info_start + COPC_INFO_BYTES:
        raise PointCloudError("truncated COPC file: the copc info record is cut short")
    root_offset, root_size = struct.unpack_from("<QQ", buffer, info_start + 40)
    pages = [(root_offset, root_size)]
    seen: set[int] = set()
    counted = 0
    while pages:
        offset, size = pages.pop()
        if offset in seen:
            raise PointCloudError(f"corrupt COPC file: the hierarchy page at {offset:,} repeats")
        seen.add(offset)
        if size % HIERARCHY_ENTRY.size or not 0 < offset <= offset + size <= source.size:
            raise PointCloudError(
                f"corrupt or truncated COPC file: a hierarchy page of {size:,} bytes at "
                f"{offset:,} lies outside the {source.size:,}-byte file"
            )
        for entry in range(size // HIERARCHY_ENTRY.size):
            *_, chunk_offset, chunk_bytes, count = HIERARCHY_ENTRY.unpack_from(
                buffer, offset + entry * HIERARCHY_ENTRY.size
            )
            if count == CHILD_PAGE:
                pages.append((chunk_offset, chunk_bytes))
                continue
            if count < 0 or (count and chunk_offset + max(chunk_bytes, 0) > source.size):
                raise PointCloudError(
                    f"corrupt or truncated COPC file: a node of {count:,} points claims bytes "
                    f"{chunk_offset:,} to {chunk_offset + chunk_bytes:,} of a "
                    f"{source.size:,}-byte file"
                )
            counted += count
    if counted != n_points:
        raise PointCloudError(
            f"the COPC header declares {n_points:,} points but its octree holds {counted:,}: "
            "the header and the point data disagree (a corrupt or edited file); export it again"
        )


def is_compressed_point_format(point_format_byte: int) -> bool:
    """The LASzip convention: bit 7 set (and bit 6 clear) in the point data format byte."""
    return bool(point_format_byte & 0x80) and not point_format_byte & 0x40


def read_las(source: Source, max_points: int | None, *, threads: int = 1) -> RawCloud:
    """Decode a LAS or LAZ file (the header says which).

    With ``threads`` >= 2, LAZ chunks are decompressed in parallel (lazrs's
    ``ParLasZipDecompressor``; when it cannot be created, e.g. without a chunk table, laspy
    falls back to the sequential decoder); with 1, sequentially.

    Raises
    ------
    PointCloudError
        Missing 'LASF' signature, malformed header, too many points, truncated body,
        absurd compression ratio, corrupt LAZ data.
    """
    with _opened_points(source, max_points, threads) as (reader, n_points, what):
        return _read_points(reader, n_points, what)


def summarise_las(source: Source, max_points: int | None, *, threads: int = 1) -> CloudSummary:
    """What :func:`read_las` and ``PointCloud.from_array`` would make of the file, as a
    :class:`~app.core.cloud_summary.CloudSummary`, decoding :data:`SUMMARY_CHUNK_POINTS` points at a
    time: memory stays at one chunk whatever the file's size (the same checks and errors).
    """
    with _opened_points(source, max_points, threads) as (reader, n_points, what):
        scales, offsets = _scales_and_offsets(reader)
        buffer = np.empty((SUMMARY_CHUNK_POINTS, 3))
        bounds = FiniteBounds()
        for _, chunk in _chunks(reader, n_points, what, SUMMARY_CHUNK_POINTS):
            xyz = buffer[: len(chunk)]
            _scale(chunk, scales, offsets, xyz)
            bounds.add(xyz)
        return bounds.summary(n_points)


def las_point_blocks(
    source: Source, max_points: int | None, chunk_points: int, *, threads: int = 1
) -> Iterator[tuple[int, NDArray[np.float64]]]:
    """The coordinates of a LAS/LAZ file ``chunk_points`` at a time (same checks as
    :func:`read_las`): memory stays at one chunk whatever the file's size.

    Yields
    ------
    start : int
        File row of the chunk's first point.
    points : ndarray, shape (k, 3), float64
        A new array per chunk.
    """
    with _opened_points(source, max_points, threads) as (reader, n_points, what):
        scales, offsets = _scales_and_offsets(reader)
        for start, chunk in _chunks(reader, n_points, what, chunk_points):
            xyz = np.empty((len(chunk), 3))
            _scale(chunk, scales, offsets, xyz)
            yield start, xyz


def declared_las_points(source: Source) -> int:
    """The point count a LAS/LAZ header declares (after the checks of :func:`read_las`)."""
    with _opened_points(source, None, 1) as (_, n_points, _):
        return n_points


def extra_dimension_names(source: Source, max_points: int | None) -> tuple[str, ...]:
    """Names of the extra-bytes dimensions the LAS/LAZ header declares (after the checks of
    :func:`read_las`, same errors)."""
    with _opened_points(source, max_points, 1) as (reader, _, _):
        return tuple(reader.header.point_format.extra_dimension_names)


@contextmanager
def _opened_points(
    source: Source, max_points: int | None, threads: int
) -> Iterator[tuple[Any, int, str]]:
    """A laspy reader positioned at the points, once the header passed every check, with the
    point count and what declared it (for messages)."""
    import laspy

    head = source.head(4)
    if head != b"LASF":
        raise PointCloudError(
            f"not a LAS/LAZ file: it does not start with the signature 'LASF' (starts with "
            f"{head!r})"
        )
    _check_header_layout(source)
    with source.stream() as stream:
        try:
            reader = laspy.open(
                stream, closefd=False, read_evlrs=False, laz_backend=_laz_backends(threads)
            )
        except Exception as exc:  # laspy raises LaspyException, ValueError, struct.error, ...
            raise PointCloudError(f"malformed LAS header: {exc}") from exc
        with reader:
            header = reader.header
            n_points = int(header.point_count)
            record_size = int(header.point_format.size)
            body_bytes = source.size - int(header.offset_to_point_data)
            what = "the LAZ header" if header.are_points_compressed else "the LAS header"
            check_point_count(n_points, max_points, what)
            if body_bytes < 0:
                raise PointCloudError(
                    f"truncated body: {what} puts the points at byte "
                    f"{header.offset_to_point_data:,} but the file has {source.size:,} bytes"
                )
            if header.are_points_compressed:
                declared = n_points * record_size
                if declared > LAZ_MAX_EXPANSION * body_bytes + 4096:
                    raise PointCloudError(
                        f"absurd LAZ header: {n_points:,} points ({declared:,} bytes) cannot "
                        f"be compressed into the {body_bytes:,} bytes present (more than "
                        f"{LAZ_MAX_EXPANSION:,}x); the file is truncated or corrupt"
                    )
                _check_laz_structure(source, header, n_points, record_size)
                if is_copc(source.buffer):
                    check_copc_hierarchy(source, n_points)
            else:
                check_point_count(
                    n_points,
                    None,
                    what,
                    available_bytes=body_bytes,
                    bytes_per_point=record_size,
                )
            yield reader, n_points, what


def _laz_backends(threads: int):  # -> tuple[laspy.LazBackend, ...], laspy imported lazily
    """The LAZ decoders laspy should try, in order: parallel first when ``threads`` >= 2.

    laspy falls back to the next one when a decoder cannot be created (the parallel one needs
    a chunk table); only the installed ones are listed, so that laspy logs no error for the
    others. An empty tuple (no LAZ decoder installed) makes laspy say so for compressed files.
    """
    import laspy

    order = (laspy.LazBackend.LazrsParallel, laspy.LazBackend.Lazrs, laspy.LazBackend.Laszip)
    if threads < 2:
        order = (laspy.LazBackend.Lazrs, laspy.LazBackend.Laszip, laspy.LazBackend.LazrsParallel)
    available = laspy.LazBackend.detect_available()
    return tuple(backend for backend in order if backend in available)


def _check_header_layout(source: Source) -> None:
    """Vet the header fields laspy loops over before it reads them.

    A corrupt VLR count (e.g. 10**9) would make laspy loop for minutes reading empty records.
    """
    if source.size < LAS_MIN_HEADER_BYTES:
        raise PointCloudError(
            f"truncated LAS header: the file has {source.size} bytes, a LAS header needs "
            f"{LAS_MIN_HEADER_BYTES}"
        )
    header_size, point_offset, n_vlrs = struct.unpack_from("<HII", source.buffer, 94)
    if not LAS_MIN_HEADER_BYTES <= header_size <= point_offset <= source.size:
        raise PointCloudError(
            f"malformed LAS header: header size {header_size:,} and point data offset "
            f"{point_offset:,} are inconsistent with a {source.size:,}-byte file"
        )
    if n_vlrs * LAS_VLR_HEADER_BYTES > point_offset - header_size:
        raise PointCloudError(
            f"malformed LAS header: {n_vlrs:,} VLRs cannot fit in the "
            f"{point_offset - header_size:,} bytes before the point data"
        )


def _check_laz_structure(source: Source, header, n_points: int, record_size: int) -> None:
    """Vet the LASzip VLR and chunk table that lazrs trusts.

    lazrs allocates from these numbers before decoding: a corrupt chunk table declaring
    billions of chunks makes it request tens of GB and *abort the process* (a Rust allocation
    failure cannot be caught), so they are checked here first.
    """
    laszip_vlrs = [vlr for vlr in header.vlrs if vlr.record_id == LASZIP_VLR_RECORD_ID]
    if not laszip_vlrs or len(getattr(laszip_vlrs[0], "record_data", b"")) < 34:
        raise PointCloudError(
            "corrupt LAZ file: the LASzip description (VLR 22204) is missing or too short"
        )
    record = laszip_vlrs[0].record_data
    chunk_size = struct.unpack_from("<I", record, 12)[0]
    n_items = struct.unpack_from("<H", record, 32)[0]
    if len(record) < 34 + 6 * n_items:
        raise PointCloudError("corrupt LAZ file: the LASzip item list is truncated")
    item_bytes = sum(struct.unpack_from("<H", record, 34 + 6 * i + 2)[0] for i in range(n_items))
    if item_bytes != record_size:
        raise PointCloudError(
            f"corrupt LAZ file: the LASzip items describe {item_bytes}-byte points but the "
            f"header's point format has {record_size}-byte points"
        )
    variable_chunks = chunk_size == 0xFFFFFFFF
    if not variable_chunks and not 0 < chunk_size <= LAZ_MAX_CHUNK_POINTS:
        raise PointCloudError(f"corrupt LAZ file: absurd chunk size {chunk_size:,} points")
    start = int(header.offset_to_point_data)
    if source.size < start + 8:
        raise PointCloudError("truncated body: the LAZ point data is missing")
    table_offset = struct.unpack_from("<q", source.buffer, start)[0]
    if table_offset == -1:
        return  # written without a chunk table (unseekable output): decoded sequentially
    if not start + 8 <= table_offset <= source.size - 8:
        raise PointCloudError(
            f"corrupt or truncated LAZ file: the chunk table offset {table_offset:,} lies "
            f"outside the point data (bytes {start + 8:,} to {source.size:,})"
        )
    version, n_chunks = struct.unpack_from("<II", source.buffer, table_offset)
    if variable_chunks:
        most_chunks = min(n_points, table_offset - start)
    else:
        most_chunks = -(-n_points // chunk_size)
    if version != 0 or n_chunks > max(most_chunks, 1):
        raise PointCloudError(
            f"corrupt or truncated LAZ file: the chunk table (version {version}) declares "
            f"{n_chunks:,} chunks where at most {most_chunks:,} are possible"
        )


def _read_points(reader, n_points: int, what: str) -> RawCloud:
    point_format = reader.header.point_format
    kept = [name for name in KEPT_STANDARD_DIMENSIONS if name in point_format.dimension_names]
    kept += list(point_format.extra_dimension_names)
    scales, offsets = _scales_and_offsets(reader)
    points = np.empty((n_points, 3), dtype=np.float64)
    attributes: dict[str, NDArray] = {}
    for n_read, chunk in _chunks(reader, n_points, what, CHUNK_POINTS):
        rows = slice(n_read, n_read + len(chunk))
        _scale(chunk, scales, offsets, points[rows])
        for name in kept:
            values = np.asarray(chunk[name])
            if name not in attributes:
                attributes[name] = np.empty((n_points, *values.shape[1:]), values.dtype)
            attributes[name][rows] = values
    return RawCloud(points, attributes)


def _chunks(reader, n_points: int, what: str, chunk_points: int) -> Iterator[tuple[int, Any]]:
    """``(first row, laspy point record)`` of up to ``chunk_points`` points at a time, until
    all ``n_points`` were decoded; corrupt or missing data is a :class:`PointCloudError`."""
    n_read = 0
    while n_read < n_points:
        try:
            chunk = reader.read_points(min(chunk_points, n_points - n_read))
        except Exception as exc:  # lazrs/laspy errors on corrupt or truncated LAZ data
            raise PointCloudError(
                f"corrupt or truncated point data after {n_read:,} of {n_points:,} points: {exc}"
            ) from exc
        if len(chunk) == 0:
            break
        yield n_read, chunk
        n_read += len(chunk)
    if n_read < n_points:
        raise PointCloudError(
            f"truncated body: {what} declares {n_points:,} points but only {n_read:,} could be "
            "read; the file was cut short: upload it again"
        )


def _scales_and_offsets(reader) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    return (
        np.asarray(reader.header.scales, dtype=np.float64),
        np.asarray(reader.header.offsets, dtype=np.float64),
    )


def _scale(
    chunk, scales: NDArray[np.float64], offsets: NDArray[np.float64], out: NDArray[np.float64]
) -> None:
    """The chunk's integer X, Y, Z as coordinates ``X * scale + offset`` into ``out``, shape
    (len(chunk), 3) float64."""
    for axis, raw_name in enumerate(("X", "Y", "Z")):
        np.multiply(chunk[raw_name], scales[axis], out=out[:, axis])
        out[:, axis] += offsets[axis]


def write_las(
    path: str, points: NDArray[np.float64], fields: Mapping[str, NDArray], compress: bool
) -> None:
    """Write LAS 1.4 (point format 6), or LAZ when ``compress``, with fields as extra bytes.

    Coordinates are stored as integers: the offset is the rounded centre of the data and the
    scale the finest of 0.1 mm, 1 mm, 1 cm, ... that keeps every coordinate in int32 range
    (0.1 mm up to a 214 km extent). Fields named like a standard dimension (``intensity``,
    ``classification``, ...) fill that dimension; the others become extra-bytes dimensions
    with their own type (bool is stored as uint8, float16 as float32).

    Raises
    ------
    PointCloudError
        Non-finite coordinates (LAS cannot store them), a field laspy cannot store.
    """
    import laspy

    if not np.isfinite(points).all():
        raise PointCloudError(
            "LAS/LAZ cannot store NaN or infinite coordinates: drop those points first"
        )
    header = laspy.LasHeader(point_format=WRITE_POINT_FORMAT, version="1.4")
    header.offsets, header.scales = _offsets_and_scales(points)
    standard = set(header.point_format.standard_dimension_names)
    extra_fields: dict[str, NDArray] = {}
    standard_fields: dict[str, NDArray] = {}
    for name, values in fields.items():
        if name.lower() in ("x", "y", "z"):
            raise PointCloudError(f"field {name!r} would overwrite a coordinate; rename it")
        values = np.asarray(values)
        if name in standard:
            standard_fields[name] = values
        else:
            extra_fields[name] = _las_compatible(name, values)
    try:
        header.add_extra_dims(
            [laspy.ExtraBytesParams(name=name, type=v.dtype) for name, v in extra_fields.items()]
        )
        las = laspy.LasData(header)
        las.x = points[:, 0]
        las.y = points[:, 1]
        las.z = points[:, 2]
        for name, values in {**standard_fields, **extra_fields}.items():
            las[name] = values
    except (ValueError, TypeError, OverflowError, laspy.LaspyException) as exc:
        raise PointCloudError(f"cannot write these fields to LAS: {exc}") from exc
    with atomic_output(path) as temporary:
        las.write(str(temporary), do_compress=compress)


def _offsets_and_scales(points: NDArray[np.float64]) -> tuple[NDArray, NDArray]:
    if len(points) == 0:
        return np.zeros(3), np.full(3, 1e-3)
    low, high = points.min(axis=0), points.max(axis=0)
    offsets = np.round((low + high) / 2.0)
    reach = np.maximum(np.abs(high - offsets), np.abs(low - offsets))
    scales = np.empty(3)
    for axis in range(3):
        scale = 1e-4
        while reach[axis] / scale >= 2**31 - 2:
            scale *= 10.0
        scales[axis] = scale
    return offsets, scales


def _las_compatible(name: str, values: NDArray) -> NDArray:
    if values.dtype == np.bool_:
        return values.astype(np.uint8)
    if values.dtype.kind == "f" and values.dtype.itemsize == 2:
        return values.astype(np.float32)
    if values.dtype.kind not in "iuf":
        raise PointCloudError(f"field {name!r} has type {values.dtype}, which LAS cannot hold")
    return values.astype(values.dtype.newbyteorder("="), copy=False)
