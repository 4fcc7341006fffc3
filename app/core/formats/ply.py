"""PLY: ascii, binary little endian and binary big endian (read), binary little endian (write).

The header is parsed by ``plyfile`` (element counts, property types, byte order). The vertex
body is then decoded in one step without a per-point Python loop:

- binary: a zero-copy ``numpy.frombuffer`` view of the (memory-mapped) file with plyfile's dtype,
  whenever the elements before ``vertex`` have no list properties (true for point clouds and for
  meshes written vertex-first); otherwise plyfile reads the whole file;
- ascii: ``numpy.loadtxt`` on the vertex rows (much faster than plyfile's row loop).

Every vertex property other than x, y, z is kept as an attribute (red/green/blue, nx/ny/nz,
intensity, label, ...). Faces and other elements are ignored.
"""

from __future__ import annotations

import io
from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

from app.core.errors import PointCloudError
from app.core.files import atomic_output
from app.core.formats._common import (
    RawCloud,
    Source,
    ascii_body,
    check_point_count,
    find_xyz_names,
    has_nonzero_bytes,
    loadtxt_problem,
    structured_attributes,
    xyz_points,
)

HEADER_LIMIT_BYTES = 1 << 20
"""Longest PLY header accepted (comments included)."""
HEADER_PEEK_BYTES = 1 << 14
"""Bytes tried first for the header (see :func:`_parse_header`)."""

VERTEX_ELEMENT_NAMES = ("vertex", "vertices", "point", "points")


def read_ply(source: Source, max_points: int | None, *, with_attributes: bool = True) -> RawCloud:
    """Decode a PLY file (any of the three encodings).

    With ``with_attributes`` False only the coordinates are decoded (for a binary file, a view
    of the memory-mapped body: nothing is copied).

    Raises
    ------
    PointCloudError
        Bad magic, malformed header, unknown property type, no vertex element or no x/y/z,
        truncated body, count mismatch, non-numeric ascii values, too many points.
    """
    import plyfile

    header, body_offset = _parse_header(source)

    elements = list(header.elements)
    vertex_position = _vertex_element_position(elements)
    vertex = elements[vertex_position]
    property_names = [prop.name for prop in vertex.properties]
    x_name, y_name, z_name = find_xyz_names(property_names, f"the PLY {vertex.name!r} element")
    has_lists = any(isinstance(prop, plyfile.PlyListProperty) for prop in vertex.properties)
    for name in (x_name, y_name, z_name):
        if isinstance(vertex.ply_property(name), plyfile.PlyListProperty):
            raise PointCloudError(f"PLY property {name!r} is a list; x, y, z must be scalars")
    check_point_count(vertex.count, max_points, "the PLY header")

    if header.text:
        data = _read_ascii_vertices(source, body_offset, elements, vertex_position, has_lists)
    else:
        data = _read_binary_vertices(
            source, body_offset, elements, vertex_position, header.byte_order, has_lists
        )
    # List properties (rare on vertices) are dropped: attributes must be (n, ...) arrays.
    scalar_fields = tuple(
        prop.name for prop in vertex.properties if not isinstance(prop, plyfile.PlyListProperty)
    )
    points = xyz_points(data[x_name], data[y_name], data[z_name])
    if not with_attributes:
        return RawCloud(points)
    attributes = structured_attributes(
        data[list(scalar_fields)] if has_lists else data, skip=(x_name, y_name, z_name)
    )
    return RawCloud(points, attributes)


def _parse_header(source: Source):  # -> (plyfile.PlyData, int), plyfile imported lazily
    """The header (plyfile's parse) and the offset of the body.

    The first :data:`HEADER_PEEK_BYTES` suffice for nearly every file; only when the header
    does not end within them is it parsed again from the first :data:`HEADER_LIMIT_BYTES`
    (copying a megabyte of a memory-mapped file costs more than the whole header parse).
    """
    import plyfile

    if source.size > HEADER_PEEK_BYTES:
        peek = source.head(HEADER_PEEK_BYTES)
        if peek.startswith(b"ply"):
            stream = io.BytesIO(peek)
            try:
                header = plyfile.PlyData._parse_header(stream)
            except Exception:  # any problem is reported from the full head below
                pass
            else:
                if stream.tell() < len(peek):  # 'end_header' and its line end are in the peek
                    return header, stream.tell()
    head = source.head(HEADER_LIMIT_BYTES)
    if not head.startswith(b"ply"):
        raise PointCloudError(
            "not a PLY file: it does not start with the magic line 'ply' "
            f"(starts with {head[:16]!r}); check the file or its format"
        )
    header_stream = io.BytesIO(head)
    try:
        header = plyfile.PlyData._parse_header(header_stream)
    except plyfile.PlyHeaderParseError as exc:
        if exc.message == "early end-of-file" and len(head) >= HEADER_LIMIT_BYTES:
            raise PointCloudError(
                f"PLY header longer than {HEADER_LIMIT_BYTES:,} bytes or without 'end_header'"
            ) from exc
        if exc.message == "early end-of-file":
            raise PointCloudError(
                "truncated PLY header: the file ends before 'end_header'"
            ) from exc
        raise PointCloudError(f"malformed PLY header (line {exc.line}): {exc.message}") from exc
    except UnicodeDecodeError as exc:
        offset = next(i for i, byte in enumerate(head) if byte > 127)
        raise PointCloudError(
            f"malformed PLY header: byte {head[offset : offset + 1]!r} at offset {offset} is "
            "not ASCII; the header must be ASCII text"
        ) from exc
    return header, header_stream.tell()


def _vertex_element_position(elements: list) -> int:
    for position, element in enumerate(elements):
        if element.name in VERTEX_ELEMENT_NAMES:
            return position
    for position, element in enumerate(elements):
        if {"x", "y", "z"} <= {prop.name.lower() for prop in element.properties}:
            return position
    names = ", ".join(element.name for element in elements) or "none"
    raise PointCloudError(
        f"the PLY file has no 'vertex' element with x, y, z properties (elements: {names})"
    )


def _read_ascii_vertices(
    source: Source, body_offset: int, elements: list, vertex_position: int, has_lists: bool
) -> NDArray:
    vertex = elements[vertex_position]
    rows_before = sum(element.count for element in elements[:vertex_position])
    body_bytes = source.size - body_offset
    # Every ascii row takes at least two bytes per value ("0 ", "0\n").
    check_point_count(
        vertex.count,
        None,
        "the PLY header",
        available_bytes=body_bytes,
        bytes_per_point=2 * len(vertex.properties),
    )
    if rows_before > body_bytes // 2:
        raise PointCloudError(
            f"truncated body: the PLY header declares {rows_before:,} rows before the vertices "
            f"but the body has only {body_bytes:,} bytes"
        )
    text = ascii_body(
        source,
        body_offset,
        "the ascii PLY body is not ASCII text: byte at offset {offset} cannot be decoded; "
        "is the 'format' line wrong (binary data declared as ascii)?",
    )
    if has_lists:
        return _read_with_plyfile(source, elements[vertex_position].name)
    stripped = text.strip()
    n_rows = stripped.count("\n") + 1 if stripped else 0
    declared_rows = sum(element.count for element in elements)
    if n_rows < rows_before + vertex.count:
        raise PointCloudError(
            f"truncated body: the PLY header declares {vertex.count:,} vertices but the body "
            f"has only {max(n_rows - rows_before, 0):,} vertex rows; the file was cut short "
            "or the 'element vertex' count is wrong"
        )
    if n_rows > declared_rows:
        raise PointCloudError(
            f"the PLY header declares {declared_rows:,} rows but the body has {n_rows:,}: "
            "fix the 'element' counts in the header"
        )
    dtype = vertex.dtype("=")
    try:
        data = np.loadtxt(
            io.StringIO(text),
            dtype=dtype,
            skiprows=rows_before,
            max_rows=vertex.count,
            ndmin=1,
            comments=None,
        )
    except ValueError as exc:
        raise PointCloudError(
            f"malformed ascii PLY vertex data: {loadtxt_problem(exc)}; each vertex row must "
            f"hold {len(vertex.properties)} numbers "
            f"({' '.join(prop.name for prop in vertex.properties)})"
        ) from exc
    return np.atleast_1d(data)


def _read_binary_vertices(
    source: Source,
    body_offset: int,
    elements: list,
    vertex_position: int,
    byte_order: str,
    has_lists: bool,
) -> NDArray:
    import plyfile

    vertex = elements[vertex_position]
    offset = body_offset
    for element in elements[:vertex_position]:
        if any(isinstance(prop, plyfile.PlyListProperty) for prop in element.properties):
            return _read_with_plyfile(source, vertex.name)
        offset += element.count * element.dtype(byte_order).itemsize
        if offset > source.size:
            raise PointCloudError(
                f"truncated body: the PLY element {element.name!r} ({element.count:,} rows) "
                "does not fit in the file; the file was cut short"
            )
    if has_lists:
        return _read_with_plyfile(source, vertex.name)
    dtype = vertex.dtype(byte_order)
    available = source.size - offset
    check_point_count(
        vertex.count,
        None,
        "the PLY header",
        available_bytes=available,
        bytes_per_point=dtype.itemsize,
    )
    is_last = vertex_position == len(elements) - 1
    surplus = available - vertex.count * dtype.itemsize
    if (
        is_last
        and surplus >= dtype.itemsize
        and has_nonzero_bytes(source.buffer, offset + vertex.count * dtype.itemsize)
    ):
        raise PointCloudError(
            f"the PLY header declares {vertex.count:,} vertices but the body holds "
            f"{available // dtype.itemsize:,}: fix the 'element vertex' count"
        )
    return np.frombuffer(source.buffer, dtype=dtype, count=vertex.count, offset=offset)


def _read_with_plyfile(source: Source, vertex_name: str) -> NDArray:
    """Fallback for layouts the fast paths do not handle (list properties before vertices)."""
    import plyfile

    try:
        with source.stream() as stream:
            ply = plyfile.PlyData.read(stream, mmap=False)
        return ply[vertex_name].data
    except plyfile.PlyElementParseError as exc:
        raise PointCloudError(
            f"malformed PLY body (element {exc.element.name if exc.element else '?'}, "
            f"row {exc.row}): {exc.message}"
        ) from exc
    except (plyfile.PlyParseError, ValueError) as exc:
        raise PointCloudError(f"malformed PLY file: {exc}") from exc


def write_ply(path: str, points: NDArray[np.float64], fields: Mapping[str, NDArray]) -> None:
    """Write binary little-endian PLY: x, y, z as float64 plus one property per field.

    Parameters
    ----------
    path : str
    points : ndarray, shape (n, 3)
    fields : mapping of str to ndarray, each shape (n,)
        bool becomes uint8, int64/uint64 become int32/uint32 when the values fit,
        float16 becomes float32 (the types PLY knows).
    """
    import plyfile

    columns: list[tuple[str, NDArray]] = [
        ("x", points[:, 0]),
        ("y", points[:, 1]),
        ("z", points[:, 2]),
    ]
    columns += [(name, _ply_compatible(name, values)) for name, values in fields.items()]
    vertex = np.empty(len(points), dtype=[(name, values.dtype) for name, values in columns])
    for name, values in columns:
        vertex[name] = values
    try:
        element = plyfile.PlyElement.describe(vertex, "vertex")
    except ValueError as exc:
        raise PointCloudError(f"cannot write these fields to PLY: {exc}") from exc
    with atomic_output(path) as temporary, open(temporary, "wb") as handle:
        plyfile.PlyData([element], text=False, byte_order="<").write(handle)


def _ply_compatible(name: str, values: NDArray) -> NDArray:
    values = np.asarray(values)
    kind, size = values.dtype.kind, values.dtype.itemsize
    if values.dtype == np.bool_:
        return values.astype(np.uint8)
    if kind in "iu" and size == 8:
        narrow = np.int32 if kind == "i" else np.uint32
        info = np.iinfo(narrow)
        if values.size and (values.min() < info.min or values.max() > info.max):
            raise PointCloudError(f"field {name!r} has 64-bit values PLY cannot hold")
        return values.astype(narrow)
    if kind == "f" and size == 2:
        return values.astype(np.float32)
    if kind not in "iuf":
        raise PointCloudError(f"field {name!r} has type {values.dtype}, which PLY cannot hold")
    return values.astype(values.dtype.newbyteorder("="), copy=False)
