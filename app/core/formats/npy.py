"""NumPy ``.npy`` and ``.npz`` files.

Accepted layouts:

- ``.npy``: a numeric array of shape (n, 3) or (n, k >= 3) (columns 0-2 are x, y, z; further
  columns are ignored), or a structured array of shape (n,) with ``x``, ``y``, ``z`` fields (other
  fields become attributes).
- ``.npz``: one of those under the key ``points`` or ``xyz``; or separate 1-D ``x``, ``y``, ``z``
  arrays; or a single array under any name (``np.savez(path, array)``). Other arrays with one
  row per point become attributes.

The array header is read with ``numpy.lib.format`` and its shape checked against ``max_points``
and against the bytes present *before* the data is read (``numpy.load`` would allocate whatever
the header claims). Pickled object arrays are refused.
"""

from __future__ import annotations

import io
import tokenize
import zipfile
from typing import BinaryIO

import numpy as np
from numpy.lib import format as npy_format
from numpy.typing import NDArray

from app.core.errors import PointCloudError
from app.core.formats._common import (
    RawCloud,
    Source,
    check_point_count,
    find_xyz_names,
    owned,
    structured_attributes,
    xyz_from_columns,
    xyz_points,
)

NPY_MAGIC = b"\x93NUMPY"
POINT_KEYS = ("points", "xyz")
# numpy.lib.format refuses longer headers by default (max_header_size); a numeric array's is ~128.
MAX_HEADER_BYTES = 10_000


def read_npy(source: Source, max_points: int | None) -> RawCloud:
    """Decode a ``.npy`` file.

    Raises
    ------
    PointCloudError
        Bad magic, malformed header, object dtype, wrong shape, too many points, truncated data.
    """
    if not source.head(6) == NPY_MAGIC:
        raise PointCloudError(
            f"not a .npy file: it does not start with '\\x93NUMPY' (starts with {source.head(8)!r})"
        )
    header_stream = io.BytesIO(source.head(65536 + 16))
    shape, fortran_order, dtype = _read_header(header_stream, "the .npy file")
    offset = header_stream.tell()
    _check_array(shape, dtype, max_points, source.size - offset, "the .npy file")
    count = int(np.prod(shape))
    flat = np.frombuffer(source.buffer, dtype=dtype, count=count, offset=offset)
    array = flat.reshape(shape[::-1]).T if fortran_order else flat.reshape(shape)
    return _cloud_from_array(array, "the .npy array")


def read_npz(source: Source, max_points: int | None) -> RawCloud:
    """Decode a ``.npz`` archive.

    Raises
    ------
    PointCloudError
        Not a zip archive, no recognisable point array, malformed member, too many points.
    """
    try:
        with source.stream() as stream, zipfile.ZipFile(stream) as archive:
            members = {
                info.filename.removesuffix(".npy"): info
                for info in archive.infolist()
                if info.filename.endswith(".npy")
            }
            if not members:
                raise PointCloudError(
                    "the .npz archive holds no arrays; save the points with "
                    "numpy.savez(path, points=array)"
                )
            key = next((k for k in POINT_KEYS if k in members), None)
            if key is not None:
                array = _read_member(archive, members[key], max_points)
                cloud = _cloud_from_array(array, f"the .npz array {key!r}")
                used = {key}
            elif {"x", "y", "z"} <= members.keys():
                columns = [_read_member(archive, members[k], max_points) for k in "xyz"]
                lengths = {column.shape for column in columns}
                if len(lengths) != 1 or columns[0].ndim != 1:
                    raise PointCloudError(
                        "the .npz arrays x, y, z must be 1-D and of equal length, got shapes "
                        + ", ".join(str(column.shape) for column in columns)
                    )
                _require_numeric(columns[0].dtype, "the .npz array 'x'")
                cloud = RawCloud(xyz_from_columns(*columns))
                used = {"x", "y", "z"}
            elif len(members) == 1:
                key = next(iter(members))
                array = _read_member(archive, members[key], max_points)
                cloud = _cloud_from_array(array, f"the .npz array {key!r}")
                used = {key}
            else:
                raise PointCloudError(
                    f"the .npz archive has no 'points' or 'xyz' array and no x/y/z arrays "
                    f"(arrays: {', '.join(sorted(members))}); save the points as "
                    "numpy.savez(path, points=array)"
                )
            n_points = len(cloud.points)
            for name in sorted(members.keys() - used):
                info = members[name]
                shape, _, _ = _member_header(archive, info)
                if shape[:1] == (n_points,) and name not in cloud.attributes:
                    values = _read_member(archive, info, max_points)
                    if values.dtype.kind in "biuf":
                        cloud.attributes[name] = owned(values)
            return cloud
    except zipfile.BadZipFile as exc:
        raise PointCloudError(f"not a valid .npz (zip) archive: {exc}") from exc
    except NotImplementedError as exc:  # zipfile: compression method or feature it lacks
        raise PointCloudError(
            f"unsupported .npz (zip) archive: {exc}; save it with numpy.savez or "
            "numpy.savez_compressed"
        ) from exc


def _read_header(stream: BinaryIO, what: str) -> tuple[tuple[int, ...], bool, np.dtype]:
    try:
        version = npy_format.read_magic(stream)
        if version not in ((1, 0), (2, 0), (3, 0)):
            raise PointCloudError(f"{what}: unsupported .npy format version {version}")
        length_field = stream.read(2 if version == (1, 0) else 4)
        header = _vetted_header(length_field, stream, version, what)
        # numpy parses the vetted bytes (its tokenizer never sees a control byte: on Python 3.12+
        # a NUL would surface as tokenize's "source code cannot contain null bytes").
        replay = io.BytesIO(length_field + header)
        if version == (1, 0):
            shape, fortran_order, dtype = npy_format.read_array_header_1_0(replay)
        else:
            shape, fortran_order, dtype = npy_format.read_array_header_2_0(replay)
    except PointCloudError:
        raise
    except (ValueError, SyntaxError, EOFError, UnicodeDecodeError, tokenize.TokenError) as exc:
        raise PointCloudError(f"malformed header in {what}: {exc}") from exc
    return tuple(int(n) for n in shape), bool(fortran_order), dtype


def _vetted_header(
    length_field: bytes, stream: BinaryIO, version: tuple[int, int], what: str
) -> bytes:
    """The header's bytes, refused if they hold a control character (other than newline).

    Parameters
    ----------
    length_field : bytes
        The little-endian header length after the magic: 2 bytes (version 1.0) or 4 bytes.
    stream : BinaryIO
        Positioned at the header's first byte; left after its last.
    version : tuple of int
        The ``.npy`` format version from the magic.
    what : str
        The array's name in messages.

    Returns
    -------
    bytes
        The header, ``length`` bytes, as numpy's header readers expect it after the length.
    """
    if len(length_field) < (2 if version == (1, 0) else 4):
        raise PointCloudError(f"malformed header in {what}: the file ends inside the header")
    length = int.from_bytes(length_field, "little")
    if length > MAX_HEADER_BYTES:
        raise PointCloudError(
            f"malformed header in {what}: it claims {length:,} bytes, more than the "
            f"{MAX_HEADER_BYTES:,} a numeric array needs"
        )
    header = stream.read(length)
    if len(header) < length:
        raise PointCloudError(f"malformed header in {what}: the file ends inside the header")
    for position, byte in enumerate(header):
        if (byte < 0x20 and byte != 0x0A) or byte == 0x7F:
            raise PointCloudError(
                f"malformed header in {what}: byte {position} of the header is {byte:#04x}, "
                "a control character; the file is corrupt (rewrite it with numpy.save)"
            )
    return header


def _check_array(
    shape: tuple[int, ...], dtype: np.dtype, max_points: int | None, available: int, what: str
) -> None:
    if dtype.hasobject:
        raise PointCloudError(
            f"{what} describes an object (pickled) array, which is not loaded for safety; "
            "save a numeric array of shape (n, 3)"
        )
    if len(shape) == 0:
        raise PointCloudError(f"{what} holds a scalar; expected an array of shape (n, 3)")
    check_point_count(shape[0], max_points, what)
    count = int(np.prod(shape))
    needed = count * dtype.itemsize
    if needed > available:
        raise PointCloudError(
            f"truncated data: {what} declares shape {shape} ({needed:,} bytes) but only "
            f"{max(available, 0):,} bytes follow; the file was cut short"
        )


def _member_header(archive: zipfile.ZipFile, info: zipfile.ZipInfo):
    with archive.open(info) as member:
        return _read_header(member, f"the .npz member {info.filename!r}")


def _read_member(
    archive: zipfile.ZipFile, info: zipfile.ZipInfo, max_points: int | None
) -> NDArray:
    what = f"the .npz member {info.filename!r}"
    with archive.open(info) as member:
        shape, fortran_order, dtype = _read_header(member, what)
        # The zip entry's declared size bounds what decompression may produce.
        _check_array(shape, dtype, max_points, info.file_size - member.tell(), what)
        count = int(np.prod(shape))
        data = member.read(count * dtype.itemsize)
    if len(data) < count * dtype.itemsize:
        raise PointCloudError(f"truncated data in {what}: the archive member was cut short")
    flat = np.frombuffer(data, dtype=dtype, count=count)
    return flat.reshape(shape[::-1]).T if fortran_order else flat.reshape(shape)


def _cloud_from_array(array: NDArray, what: str) -> RawCloud:
    if array.dtype.names:
        if array.ndim != 1:
            raise PointCloudError(
                f"{what} is a structured array of shape {array.shape}; expected shape (n,)"
            )
        x_name, y_name, z_name = find_xyz_names(list(array.dtype.names), what)
        for name in (x_name, y_name, z_name):
            _require_numeric(array.dtype[name], f"{what} field {name!r}")
        points = xyz_points(array[x_name], array[y_name], array[z_name])
        attributes = {
            name: values
            for name, values in structured_attributes(array, (x_name, y_name, z_name)).items()
            if values.dtype.kind in "biuf"
        }
        return RawCloud(points, attributes)
    _require_numeric(array.dtype, what)
    if array.ndim != 2 or array.shape[1] < 3:
        raise PointCloudError(
            f"{what} has shape {array.shape}; expected (n, 3) (or (n, k) with k >= 3, "
            "x y z first) or a structured array with x, y, z fields"
        )
    # a view of the buffer when the columns allow it (no copy: PointCloud.from_array widens
    # it once; summarise_array visits it a block at a time)
    return RawCloud(xyz_points(array[:, 0], array[:, 1], array[:, 2]))


def _require_numeric(dtype: np.dtype, what: str) -> None:
    if dtype.kind not in "iuf":
        raise PointCloudError(
            f"{what} has dtype {dtype}, expected numbers (float or integer coordinates)"
        )
