"""Point-cloud files as bytes, one writer per format (the reference libraries write them).

PLY through plyfile, PCD through pypcd4 (or by hand for record layouts pypcd4 cannot write),
LAS/LAZ through laspy, E57 through pye57, NPY/NPZ through numpy, XYZ/CSV as text.  Each takes
(n, 3) points and the options the tests need; write to disk with
``path.write_bytes(ply_bytes(points))``.
"""

from __future__ import annotations

import io
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path

import laspy
import numpy as np
import plyfile
import pye57
import pypcd4
from numpy.typing import NDArray

from app.testing.scenes import room_points

PLY_BYTE_ORDERS = {"binary_big_endian": ">", "binary_little_endian": "<", "ascii": "="}
PCD_TYPE_CODES = {"f": "F", "u": "U", "i": "I"}


def ply_bytes(
    points: NDArray,
    encoding: str = "binary_little_endian",
    coordinate_type: str = "f4",
    extra: dict[str, NDArray] | None = None,
    other_elements: Sequence[plyfile.PlyElement] = (),
    elements_before: Sequence[plyfile.PlyElement] = (),
    comments: Sequence[str] = (),
) -> bytes:
    """A PLY file of ``points``: (n, 3) coordinates, or a structured array of vertex records.

    Coordinates are written as ``coordinate_type`` with the ``extra`` properties after them;
    records are written as they are (their field order and types kept).  ``encoding`` is
    ``binary_little_endian``, ``binary_big_endian`` or ``ascii``.
    """
    if points.dtype.names is not None:
        vertex = points
    else:
        extra = extra or {}
        dtype = [("x", coordinate_type), ("y", coordinate_type), ("z", coordinate_type)]
        dtype += [(name, values.dtype.str) for name, values in extra.items()]
        vertex = np.empty(len(points), dtype=dtype)
        for axis, name in enumerate("xyz"):
            vertex[name] = points[:, axis]
        for name, values in extra.items():
            vertex[name] = values
    elements = [*elements_before, plyfile.PlyElement.describe(vertex, "vertex"), *other_elements]
    data = plyfile.PlyData(
        elements,
        text=encoding == "ascii",
        byte_order=PLY_BYTE_ORDERS[encoding],
        comments=list(comments),
    )
    stream = io.BytesIO()
    data.write(stream)
    return stream.getvalue()


def ply_of_size(size: int, seed: int = 3) -> bytes:
    """A valid binary PLY of a room of exactly ``size`` bytes (a header comment takes the slack)."""
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment {pad}\nelement vertex {n}\n"
        "property float x\nproperty float y\nproperty float z\nend_header\n"
    )
    n_points = (size - len(header.format(pad="", n=10**6))) // 12
    body = room_points(n_points, seed=seed).astype("<f4").tobytes()
    padding = size - len(body) - len(header.format(pad="", n=n_points))
    content = header.format(pad="x" * padding, n=n_points).encode() + body
    assert len(content) == size, (len(content), size)
    return content


def pcd_bytes(
    points: NDArray,
    encoding: str = "binary",
    extra: dict[str, NDArray] | None = None,
    viewpoint: Sequence[float] | None = None,
) -> bytes:
    """A PCD file of ``points``: (n, 3) coordinates, or a structured array of records.

    Coordinates are written as float32 with the ``extra`` fields after them, by pypcd4 (any
    ``encoding``: ``ascii``, ``binary``, ``binary_compressed``).  Records (any field order,
    ``COUNT`` > 1, padding) are written by hand, ``binary`` or ``binary_compressed``.
    ``viewpoint`` (7 numbers: position, then quaternion) replaces the default VIEWPOINT.
    """
    if points.dtype.names is not None:
        return _pcd_records_bytes(points, encoding, viewpoint or (0, 0, 0, 1, 0, 0, 0))
    extra = extra or {}
    columns = [
        points[:, 0].astype(np.float32),
        points[:, 1].astype(np.float32),
        points[:, 2].astype(np.float32),
        *extra.values(),
    ]
    types = [np.float32] * 3 + [values.dtype.type for values in extra.values()]
    cloud = pypcd4.PointCloud.from_points(columns, ("x", "y", "z", *extra), types)
    stream = io.BytesIO()
    cloud.save(stream, encoding=pypcd4.Encoding(encoding))
    content = stream.getvalue()
    if viewpoint is not None:
        default = b"VIEWPOINT 0.0 0.0 0.0 1.0 0.0 0.0 0.0"
        content = content.replace(default, b"VIEWPOINT " + " ".join(map(str, viewpoint)).encode())
    # pypcd4 silently falls back to binary when LZF cannot shrink the data (random floats).
    assert f"DATA {encoding}\n".encode() in content, "use compressible test data"
    return content


def _pcd_records_bytes(records: NDArray, encoding: str, viewpoint: Sequence[float]) -> bytes:
    """A PCD file of structured ``records`` (FIELDS, SIZE, TYPE, COUNT from their dtype)."""
    fields = [records.dtype.fields[name][0] for name in records.dtype.names]
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
        f"FIELDS {' '.join(records.dtype.names)}\n"
        f"SIZE {' '.join(str(field.base.itemsize) for field in fields)}\n"
        f"TYPE {' '.join(PCD_TYPE_CODES[field.base.kind] for field in fields)}\n"
        f"COUNT {' '.join(str(int(np.prod(field.shape))) for field in fields)}\n"
        f"WIDTH {len(records)}\nHEIGHT 1\nVIEWPOINT {' '.join(map(str, viewpoint))}\n"
        f"POINTS {len(records)}\nDATA {encoding}\n"
    )
    if encoding == "binary":
        return header.encode() + records.tobytes()
    import lzf

    columns = b"".join(
        np.ascontiguousarray(records[name]).tobytes() for name in records.dtype.names
    )
    compressed = lzf.compress(columns, 2 * len(columns) + 64)
    return header.encode() + np.array([len(compressed), len(columns)], "<u4").tobytes() + compressed


def las_bytes(
    points: NDArray[np.float64],
    compress: bool = False,
    point_format: int = 3,
    version: str = "1.2",
    scale: float = 0.001,
    extra: dict[str, NDArray] | None = None,
    gps_time: NDArray[np.float64] | None = None,
) -> bytes:
    """A LAS (LAZ when ``compress``) file of (n, 3) ``points`` at ``scale`` resolution.

    Intensity counts up, classification is 2 (ground) and, in formats with colour, red counts
    up; ``extra`` adds extra-bytes dimensions; ``gps_time`` (n,) fills the per-point GPS time of
    the formats that have one (1, 3, 5-10).
    """
    header = laspy.LasHeader(point_format=point_format, version=version)
    header.scales = np.full(3, scale)
    header.offsets = np.floor(points.min(axis=0))
    if extra:
        header.add_extra_dims([laspy.ExtraBytesParams(name, v.dtype) for name, v in extra.items()])
    las = laspy.LasData(header)
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    las.intensity = np.arange(len(points), dtype=np.uint16)
    las.classification = np.full(len(points), 2, dtype=np.uint8)
    if point_format in (2, 3, 7, 8):
        las.red = np.arange(len(points), dtype=np.uint16) * 100
    for name, values in (extra or {}).items():
        las[name] = values
    if gps_time is not None:
        las.gps_time = gps_time
    stream = io.BytesIO()
    las.write(stream, do_compress=compress)
    return stream.getvalue()


def e57_bytes(
    scans: Sequence[NDArray[np.float64]],
    poses: Sequence[tuple[Sequence[float], Sequence[float]]] | None = None,
    intensity: bool = False,
    invalid: Sequence[NDArray[np.bool_] | None] | None = None,
) -> bytes:
    """An E57 file with one scan per (n_i, 3) array of ``scans``, each in its sensor's frame.

    ``poses[i]`` is ``(rotation quaternion w, x, y, z; translation x, y, z)`` placing scan i in
    the file's frame (default: the identity); ``intensity`` adds an intensity that counts up;
    ``invalid[i]`` flags points of scan i invalid (``cartesianInvalidState``).
    """
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "scans.e57"
        with pye57.E57(str(path), mode="w") as writer:
            for index, points in enumerate(scans):
                data = {
                    "cartesianX": points[:, 0],
                    "cartesianY": points[:, 1],
                    "cartesianZ": points[:, 2],
                }
                if intensity:
                    data["intensity"] = np.arange(len(points), dtype=np.float32)
                if invalid is not None and invalid[index] is not None:
                    data["cartesianInvalidState"] = np.asarray(invalid[index], dtype=np.int8)
                rotation, translation = ((1, 0, 0, 0), (0, 0, 0)) if poses is None else poses[index]
                writer.write_scan_raw(
                    data,
                    name=f"scan {index}",
                    rotation=np.asarray(rotation, dtype=np.float64),
                    translation=np.asarray(translation, dtype=np.float64),
                )
        return path.read_bytes()


def npy_bytes(array: NDArray) -> bytes:
    """An NPY file of ``array`` (pickles allowed, to build refused inputs)."""
    stream = io.BytesIO()
    np.save(stream, array, allow_pickle=True)
    return stream.getvalue()


def npz_bytes(**arrays: NDArray) -> bytes:
    """A compressed NPZ file holding ``arrays`` under their keyword names."""
    stream = io.BytesIO()
    np.savez_compressed(stream, **arrays)
    return stream.getvalue()


def text_bytes(points: NDArray, delimiter: str = " ", header: str | None = None) -> bytes:
    """An XYZ/CSV text file: one row per point, values as ``repr``, an optional header line."""
    lines = [header] if header is not None else []
    lines += [delimiter.join(repr(float(v)) for v in row) for row in points]
    return ("\n".join(lines) + "\n").encode()


def chunked(content: bytes, chunk_size: int = 16_384) -> Iterator[bytes]:
    """The body as a generator: httpx sends it chunked, without ``Content-Length``."""
    for start in range(0, len(content), chunk_size):
        yield content[start : start + chunk_size]


def room_ply(seed: int, *, with_box: bool = False, n_points: int = 1500) -> bytes:
    """A binary PLY of a room's floor and two walls (3 mm noise); ``with_box`` adds a box."""
    return ply_bytes(room_points(n_points, seed, noise=0.003, with_box=with_box))
