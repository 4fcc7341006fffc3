"""E57 (ASTM E2807), the exchange format of terrestrial laser scanners, read with ``pye57``.

An E57 file holds one or more scans (``data3D`` entries), each in its own frame with a pose
(rotation quaternion and translation) that places it in the file's frame. The reader returns
every scan's points in the file's frame, one cloud, with

- ``station_index`` (int32): which scan took each point (see
  :data:`app.core.localise.station_assignment.STATION_INDEX_ATTRIBUTE`), and
- ``sensor_origin``: each scan's origin in the file's frame, the translation of its pose
  (shape (3,) for one scan, (k, 3) for k scans; a scan without a pose stands at 0, 0, 0).

Cartesian and spherical coordinates are read; points flagged invalid are skipped; ``intensity``
is kept when every scan has it, and so are per-point times (``timeStamp``, seconds, float64: a
moving sensor's trajectory places each point by them, :mod:`app.core.trajectory_poses`) when
every scan has them and none is flagged invalid (``isTimeStampInvalid``). Scans without points
are left out (and their origins with them). libE57Format reads from a file path: content given
as bytes is written to a temporary file first.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from app.core.errors import PointCloudError
from app.core.formats._common import RawCloud, Source, check_point_count

E57_SIGNATURE = b"ASTM-E57"
"""The first bytes of every E57 file (its physical header's file signature)."""

CARTESIAN_FIELDS = ("cartesianX", "cartesianY", "cartesianZ")
SPHERICAL_FIELDS = ("sphericalRange", "sphericalAzimuth", "sphericalElevation")
TIME_FIELD = "timeStamp"
TIME_INVALID_FIELD = "isTimeStampInvalid"


def read_e57(source: Source, max_points: int | None) -> RawCloud:
    """Decode every scan of an E57 file into the file's frame.

    Returns
    -------
    RawCloud
        ``points`` (n, 3) float64 in the file's frame; ``attributes["station_index"]`` (n,)
        int32; ``attributes["intensity"]`` (n,) and ``attributes["timeStamp"]`` (n,) float64
        when every scan has them; ``sensor_origin``
        (3,) for one scan or (k, 3) for k scans with points.

    Raises
    ------
    PointCloudError
        Not an E57 file, a truncated or corrupt one (libE57Format's reason), no scan, no
        points, a scan without coordinates, too many points.
    """
    import pye57

    head = source.head(len(E57_SIGNATURE))
    if head != E57_SIGNATURE:
        raise PointCloudError(
            f"not an E57 file: it does not start with the signature 'ASTM-E57' (starts with "
            f"{head!r})"
        )
    with _as_path(source) as path:
        try:
            reader = pye57.E57(str(path))
        except Exception as exc:  # libE57Format's E57Exception: truncated, bad checksum, ...
            raise PointCloudError(f"unreadable E57 file: {_reason(exc)}") from exc
        try:
            return _read_scans(reader, max_points)
        finally:
            reader.close()


def _read_scans(reader, max_points: int | None) -> RawCloud:  # reader: pye57.E57
    try:
        headers = [reader.get_header(index) for index in range(reader.scan_count)]
        fields = [set(header.point_fields) for header in headers]
        counts = [int(header.point_count) for header in headers]
    except Exception as exc:
        raise PointCloudError(f"malformed E57 scan header: {_reason(exc)}") from exc
    if not headers:
        raise PointCloudError("the E57 file holds no scan (its data3D list is empty): no points")
    check_point_count(sum(counts), max_points, "the E57 scan headers")
    for index, present in enumerate(fields):
        if not (set(CARTESIAN_FIELDS) <= present or set(SPHERICAL_FIELDS) <= present):
            raise PointCloudError(
                f"E57 scan {index} has neither cartesianX/Y/Z nor sphericalRange/Azimuth/"
                f"Elevation fields (it has {sorted(present)}): no coordinates to read"
            )
    with_intensity = all("intensity" in present for present in fields)
    with_times = all(TIME_FIELD in present for present in fields)
    points: list[NDArray[np.float64]] = []
    intensities: list[NDArray] = []
    times: list[NDArray[np.float64] | None] = []
    origins: list[NDArray[np.float64]] = []
    for index, header in enumerate(headers):
        if counts[index] == 0:
            continue
        try:
            data = reader.read_scan(
                index, intensity=with_intensity, transform=True, ignore_missing_fields=True
            )
            origin = _scan_origin(header)
            scan_times = _scan_times(reader, header) if with_times else None
        except Exception as exc:
            raise PointCloudError(f"cannot read E57 scan {index}: {_reason(exc)}") from exc
        xyz = np.column_stack(
            [np.asarray(data[name], dtype=np.float64) for name in CARTESIAN_FIELDS]
        )
        if len(xyz) == 0:
            continue
        points.append(xyz)
        origins.append(origin)
        if with_intensity:
            intensities.append(np.asarray(data["intensity"]))
        times.append(scan_times)
    if not points:
        raise PointCloudError(
            f"the E57 file holds no points: its {len(headers)} scan(s) are empty or every point "
            "is flagged invalid"
        )
    station = np.concatenate(
        [np.full(len(block), number, dtype=np.int32) for number, block in enumerate(points)]
    )
    attributes: dict[str, NDArray] = {"station_index": station}
    if with_intensity:
        attributes["intensity"] = np.concatenate(intensities)
    if with_times and all(block is not None for block in times):
        attributes[TIME_FIELD] = np.concatenate(times)  # type: ignore[arg-type]
    origin_array = np.vstack(origins)
    return RawCloud(
        np.vstack(points), attributes, origin_array[0] if len(origins) == 1 else origin_array
    )


def _scan_times(reader, header) -> NDArray[np.float64] | None:  # pye57.E57, pye57.ScanHeader
    """The scan's per-point ``timeStamp`` values (n,), float64, for the points ``read_scan``
    keeps (those not flagged invalid), or None when a kept point's time is flagged invalid.

    pye57's ``read_scan`` does not read ``timeStamp``: it is read here with libE57Format's own
    buffers, together with the validity flags ``read_scan`` filters the points by.
    """
    from pye57 import libe57

    present = set(header.point_fields)
    count = int(header.point_count)
    coordinates_valid = (
        "cartesianInvalidState" if set(CARTESIAN_FIELDS) <= present else "sphericalInvalidState"
    )
    names = [TIME_FIELD] + [
        name for name in (coordinates_valid, TIME_INVALID_FIELD) if name in present
    ]
    arrays = {
        name: np.empty(count, dtype=np.float64 if name == TIME_FIELD else np.int8) for name in names
    }
    buffers = libe57.VectorSourceDestBuffer()
    for name in names:
        buffers.append(
            libe57.SourceDestBuffer(reader.image_file, name, arrays[name], count, True, True)
        )
    scan_reader = header.points.reader(buffers)
    try:
        scan_reader.read()
    finally:
        scan_reader.close()
    kept = np.ones(count, dtype=bool)
    if coordinates_valid in arrays:
        kept = arrays[coordinates_valid] == 0
    if TIME_INVALID_FIELD in arrays and (arrays[TIME_INVALID_FIELD][kept] != 0).any():
        return None
    return arrays[TIME_FIELD][kept]


def _scan_origin(header) -> NDArray[np.float64]:  # header: pye57.ScanHeader
    """Where the scanner stood in the file's frame: its pose's translation (0, 0, 0 without)."""
    if not header.has_pose():
        return np.zeros(3)
    translation = np.asarray(header.translation, dtype=np.float64).reshape(3)  # 0s if absent
    if not np.isfinite(translation).all():
        raise PointCloudError(f"the scan's pose translation {translation.tolist()} is not finite")
    return translation


def _reason(exc: Exception) -> str:
    """The first line of libE57Format's message (the rest is debug context)."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    return lines[0] if lines else type(exc).__name__


@contextmanager
def _as_path(source: Source) -> Iterator[Path]:
    """The content as a file libE57Format can open: the source's own file, else a temporary."""
    if source.path is not None:
        yield source.path
        return
    handle, name = tempfile.mkstemp(suffix=".e57", prefix="scandiff-")
    try:
        with os.fdopen(handle, "wb") as stream:
            stream.write(source.buffer)
        yield Path(name)
    finally:
        Path(name).unlink(missing_ok=True)
