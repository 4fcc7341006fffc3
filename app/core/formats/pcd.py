"""PCD (the Point Cloud Library's format): ascii, binary and binary_compressed.

The header lines are parsed and validated by ``pypcd4`` (``MetaData.parse_header``), which also
builds the numpy dtype of a point record. The body is decoded here with numpy so that every size
can be checked *before* anything is allocated or decompressed (pypcd4 would trust the header):

- binary: zero-copy ``numpy.frombuffer`` of the (memory-mapped) file;
- binary_compressed: the declared sizes are checked against ``POINTS`` x record size, against the
  bytes present and against LZF's maximum expansion (a decompression bomb is refused unread),
  then LZF-decompressed (``lzf``, pypcd4's codec) and split into its per-field columns;
- ascii: ``numpy.loadtxt``.

Fields other than x, y, z become attributes; ``rgb``/``rgba`` (packed 0x00RRGGBB, declared as
float32 or uint32) are kept as **uint32** ``rgb``/``rgba``; fields with ``COUNT`` > 1 (e.g.
histograms) become (n, count) arrays; ``_`` padding fields are skipped.

``VIEWPOINT tx ty tz qw qx qy qz`` is the acquisition pose in the points' frame (PCL's
``sensor_origin_``/``sensor_orientation_``). Its translation becomes ``sensor_origin`` unless the
viewpoint is PCL's default ``0 0 0 1 0 0 0``: nearly every writer emits that default whether or
not the sensor really sat at the origin, so it is read as "unknown" (``None``). The orientation
is not kept (nothing downstream uses it).

pypcd4 imports pydantic, so it is imported only when a PCD file is read (the core's import
wall forbids pydantic at import time).
"""

from __future__ import annotations

import io
import struct

import numpy as np
from numpy.typing import NDArray

from app.core.errors import PointCloudError
from app.core.formats._common import (
    RawCloud,
    Source,
    ascii_body,
    check_point_count,
    find_xyz_names,
    has_nonzero_bytes,
    loadtxt_problem,
    owned,
    xyz_points,
)

HEADER_LIMIT_BYTES = 64 * 1024
"""Longest PCD header accepted (comment lines included)."""

HEADER_KEYWORDS = (
    "VERSION",
    "FIELDS",
    "SIZE",
    "TYPE",
    "COUNT",
    "WIDTH",
    "HEIGHT",
    "VIEWPOINT",
    "POINTS",
    "DATA",
)
DEFAULT_VIEWPOINT = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
VALID_TYPE_SIZES = {"F": (4, 8), "U": (1, 2, 4, 8), "I": (1, 2, 4, 8)}
LZF_MAX_EXPANSION = 100
"""LZF encodes at most 264 bytes per 3-byte back-reference (x88); more is corrupt or a bomb."""
PACKED_COLOUR_FIELDS = ("rgb", "rgba")
PADDING_PREFIXES = ("_", "#$%&~~")  # pypcd4 renames '_' padding fields to '#$%&~~<random>'


def read_pcd(source: Source, max_points: int | None) -> RawCloud:
    """Decode a PCD file.

    Raises
    ------
    PointCloudError
        No PCD header, unknown keyword, unknown field type/size, inconsistent counts, no x/y/z,
        too many points, truncated or surplus body, corrupt or absurd compressed block.
    """
    lines, data_offset = _split_header(source)
    metadata = _parse_metadata(lines)
    field_names = list(metadata.fields)
    x_name, y_name, z_name = find_xyz_names(field_names, "the PCD header's FIELDS")
    for name in (x_name, y_name, z_name):
        if metadata.count[field_names.index(name)] != 1:
            raise PointCloudError(f"PCD field {name!r} has COUNT > 1; x, y, z must be scalars")
    check_point_count(metadata.points, max_points, "the PCD header (POINTS)")
    dtype = metadata.build_dtype()
    encoding = metadata.data.value
    if metadata.points == 0:
        columns = {name: np.empty(0, dtype[name]) for name in dtype.names}
    elif encoding == "ascii":
        columns = _read_ascii(source, data_offset, metadata, dtype)
    elif encoding == "binary":
        columns = _read_binary(source, data_offset, metadata.points, dtype)
    else:
        columns = _read_compressed(source, data_offset, metadata.points, dtype)

    points = xyz_points(columns[x_name], columns[y_name], columns[z_name])
    attributes: dict[str, NDArray] = {}
    for name, count in zip(metadata.fields, metadata.count, strict=True):
        if name in (x_name, y_name, z_name) or name.startswith(PADDING_PREFIXES):
            continue
        if count == 1:
            values = owned(columns[name])
        else:
            values = np.stack([columns[f"{name}__{i:04d}"] for i in range(count)], axis=1)
        if name.lower() in PACKED_COLOUR_FIELDS and values.dtype.itemsize == 4:
            values = owned(values).view(np.uint32)
        attributes[name] = values
    viewpoint = tuple(float(v) for v in metadata.viewpoint)
    sensor_origin = None if viewpoint == DEFAULT_VIEWPOINT else np.array(viewpoint[:3])
    return RawCloud(points, attributes, sensor_origin)


def _split_header(source: Source) -> tuple[list[str], int]:
    """The header's non-comment lines (through ``DATA``) and the offset of the body."""
    head = source.head(HEADER_LIMIT_BYTES)
    lines: list[str] = []
    position = 0
    while True:
        end = head.find(b"\n", position)
        if end < 0:
            if lines:
                raise PointCloudError(
                    "truncated PCD header: no 'DATA' line"
                    + (
                        f" within the first {HEADER_LIMIT_BYTES:,} bytes"
                        if len(head) == HEADER_LIMIT_BYTES
                        else ""
                    )
                    + "; the file was cut short or is not a PCD file"
                )
            raise PointCloudError(f"not a PCD file: no header line (starts with {head[:16]!r})")
        raw_line = head[position:end]
        try:
            line = raw_line.decode("ascii").strip()
        except UnicodeDecodeError as exc:
            raise PointCloudError(
                f"malformed PCD header: line {len(lines) + 1} is not ASCII text "
                f"({raw_line[:32]!r}); is this really a PCD file?"
            ) from exc
        data_start = end + 1
        position = data_start
        if not line or line.startswith("#"):
            continue
        keyword = line.split(None, 1)[0].upper()
        if keyword not in HEADER_KEYWORDS:
            if not lines:
                raise PointCloudError(
                    f"not a PCD file: the first header line is {line[:40]!r}, expected "
                    "'VERSION' or 'FIELDS'"
                )
            raise PointCloudError(
                f"malformed PCD header: unknown line {line[:40]!r} "
                f"(expected one of {', '.join(HEADER_KEYWORDS)})"
            )
        lines.append(line)
        if keyword == "DATA":
            return lines, data_start


def _parse_metadata(lines: list[str]):  # -> pypcd4.MetaData (imported lazily)
    from pypcd4.pypcd4 import MetaData

    values = {line.split(None, 1)[0].upper(): line.split()[1:] for line in lines}
    for keyword in ("FIELDS", "SIZE", "TYPE", "DATA"):
        if not values.get(keyword):
            raise PointCloudError(f"malformed PCD header: the {keyword} line is missing or empty")
    fields = values["FIELDS"]
    n_fields = len(fields)
    counts = values.get("COUNT") or ["1"] * n_fields
    for keyword, items in (("SIZE", values["SIZE"]), ("TYPE", values["TYPE"]), ("COUNT", counts)):
        if len(items) != n_fields:
            raise PointCloudError(
                f"malformed PCD header: FIELDS lists {n_fields} names but {keyword} lists "
                f"{len(items)} values"
            )
    for name, type_code, size in zip(fields, values["TYPE"], values["SIZE"], strict=True):
        allowed = VALID_TYPE_SIZES.get(type_code.upper())
        if allowed is None:
            raise PointCloudError(
                f"unknown PCD field type {type_code!r} for field {name!r}: TYPE must be F "
                "(float), U (unsigned) or I (signed)"
            )
        if not size.isdigit() or int(size) not in allowed:
            raise PointCloudError(
                f"unsupported PCD field type: field {name!r} is {type_code} of SIZE {size}; "
                f"{type_code} supports sizes {', '.join(map(str, allowed))}"
            )
    encoding = values["DATA"][0].lower()
    if encoding not in ("ascii", "binary", "binary_compressed", "binaryscompressed"):
        raise PointCloudError(
            f"unknown PCD DATA encoding {values['DATA'][0]!r}: expected ascii, binary or "
            "binary_compressed"
        )
    width, height, points = (values.get(k, [None])[0] for k in ("WIDTH", "HEIGHT", "POINTS"))
    try:
        n_height = int(height) if height is not None else 1
        n_points = int(points) if points is not None else None
        n_width = int(width) if width is not None else None
    except ValueError as exc:
        raise PointCloudError(
            f"malformed PCD header: WIDTH/HEIGHT/POINTS must be integers ({exc})"
        ) from exc
    if n_points is None and n_width is None:
        raise PointCloudError("malformed PCD header: neither POINTS nor WIDTH is given")
    if n_width is None:
        n_width = n_points // max(n_height, 1) if n_points is not None else 0
    if n_points is None:
        n_points = n_width * n_height
    if n_width * n_height != n_points:
        raise PointCloudError(
            f"PCD header count mismatch: WIDTH x HEIGHT = {n_width} x {n_height} = "
            f"{n_width * n_height:,} but POINTS = {n_points:,}; fix the header"
        )
    normalised = [
        "FIELDS " + " ".join(fields),
        "SIZE " + " ".join(values["SIZE"]),
        "TYPE " + " ".join(t.upper() for t in values["TYPE"]),
        "COUNT " + " ".join(counts),
        f"WIDTH {n_width}",
        f"HEIGHT {n_height}",
        f"POINTS {n_points}",
        f"DATA {encoding}",
    ]
    if "VIEWPOINT" in values:
        normalised.append("VIEWPOINT " + " ".join(values["VIEWPOINT"]))
    try:
        return MetaData.parse_header(normalised)
    except ValueError as exc:  # pydantic.ValidationError is a ValueError
        summary = "; ".join(str(exc).splitlines()[1:3]) or str(exc)
        raise PointCloudError(f"malformed PCD header: {summary}") from exc


def _read_binary(source: Source, offset: int, n_points: int, dtype: np.dtype) -> dict[str, NDArray]:
    available = source.size - offset
    check_point_count(
        n_points,
        None,
        "the PCD header (POINTS)",
        available_bytes=available,
        bytes_per_point=dtype.itemsize,
    )
    end = offset + n_points * dtype.itemsize
    if available - n_points * dtype.itemsize >= dtype.itemsize and has_nonzero_bytes(
        source.buffer, end
    ):
        # PCL pads binary files with zero bytes; non-zero records beyond POINTS are points.
        raise PointCloudError(
            f"PCD header count mismatch: POINTS = {n_points:,} but the binary body holds "
            f"{available // dtype.itemsize:,} records of {dtype.itemsize} bytes; fix POINTS "
            "(and WIDTH) or the FIELDS/SIZE/COUNT lines"
        )
    records = np.frombuffer(source.buffer, dtype=dtype, count=n_points, offset=offset)
    return {name: records[name] for name in dtype.names}


def _read_compressed(
    source: Source, offset: int, n_points: int, dtype: np.dtype
) -> dict[str, NDArray]:
    import lzf

    available = source.size - offset
    if available < 8:
        raise PointCloudError(
            "truncated body: the binary_compressed PCD body lacks its 8-byte size prefix"
        )
    compressed_size, uncompressed_size = struct.unpack_from("<II", source.buffer, offset)
    expected = n_points * dtype.itemsize
    if uncompressed_size != expected:
        raise PointCloudError(
            f"PCD header count mismatch: POINTS = {n_points:,} records of {dtype.itemsize} "
            f"bytes need {expected:,} bytes but the compressed block declares "
            f"{uncompressed_size:,} uncompressed bytes"
        )
    if compressed_size > available - 8:
        raise PointCloudError(
            f"truncated body: the compressed PCD block declares {compressed_size:,} bytes but "
            f"only {available - 8:,} follow; the file was cut short"
        )
    if uncompressed_size > LZF_MAX_EXPANSION * compressed_size + 64:
        raise PointCloudError(
            f"absurd compressed PCD block: {compressed_size:,} compressed bytes cannot expand "
            f"to the declared {uncompressed_size:,} bytes (LZF expands at most "
            f"{LZF_MAX_EXPANSION}x); the file is corrupt"
        )
    start = offset + 8
    compressed = bytes(source.buffer[start : start + compressed_size])
    try:
        decompressed = lzf.decompress(compressed, uncompressed_size)
    except ValueError as exc:
        raise PointCloudError(f"corrupt compressed PCD data: {exc}") from exc
    if decompressed is None or len(decompressed) != uncompressed_size:
        raise PointCloudError(
            "corrupt compressed PCD data: it does not decompress to the declared "
            f"{uncompressed_size:,} bytes"
        )
    columns: dict[str, NDArray] = {}
    position = 0
    for name in dtype.names:
        field_dtype = dtype[name]
        columns[name] = np.frombuffer(
            decompressed, dtype=field_dtype, count=n_points, offset=position
        )
        position += field_dtype.itemsize * n_points
    return columns


def _read_ascii(source: Source, offset: int, metadata, dtype: np.dtype) -> dict[str, NDArray]:
    n_points = metadata.points
    n_columns = len(dtype.names)
    # Every ascii value takes at least two bytes ("0 " or "0\n").
    check_point_count(
        n_points,
        None,
        "the PCD header (POINTS)",
        available_bytes=source.size - offset,
        bytes_per_point=2 * n_columns,
    )
    text = ascii_body(
        source,
        offset,
        "the ascii PCD body is not ASCII text (byte offset {offset}); "
        "is DATA wrong (binary data declared as ascii)?",
    )
    try:
        table = np.loadtxt(io.StringIO(text), dtype=np.float64, ndmin=2, comments=None)
    except ValueError as exc:
        raise PointCloudError(
            f"malformed ascii PCD data: {loadtxt_problem(exc)}; each row must hold "
            f"{n_columns} numbers"
        ) from exc
    if table.shape[0] != n_points:
        raise PointCloudError(
            f"PCD header count mismatch: POINTS = {n_points:,} but the ascii body has "
            f"{table.shape[0]:,} rows"
            + ("; the file was cut short" if table.shape[0] < n_points else "")
        )
    if table.shape[1] != n_columns:
        raise PointCloudError(
            f"PCD header/body mismatch: the header describes {n_columns} values per point "
            f"but the ascii rows hold {table.shape[1]}"
        )
    columns: dict[str, NDArray] = {}
    for index, name in enumerate(dtype.names):
        column = table[:, index]
        field_dtype = dtype[name]
        base_name = name.split("__")[0].lower()
        if base_name in PACKED_COLOUR_FIELDS and field_dtype == np.float32:
            # PCL writes packed colours in ascii as the uint32 integer even for TYPE F.
            if np.all(np.isfinite(column)) and np.all(column == np.floor(column)):
                columns[name] = column.astype(np.uint32).view(np.float32)
            else:
                columns[name] = column.astype(np.float32)
        elif field_dtype.kind in "iu":
            if not np.all(np.isfinite(column)) or np.any(column != np.floor(column)):
                raise PointCloudError(
                    f"malformed ascii PCD data: field {name!r} is declared integer "
                    "(TYPE U/I) but holds non-integer values"
                )
            columns[name] = column.astype(field_dtype)
        else:
            columns[name] = column.astype(field_dtype)
    return columns
