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

SCAN_CHUNK_POINTS = 1 << 18
"""Points of a scan decoded at a time (libE57Format reads a scan's records in pieces)."""

CARTESIAN_FIELDS = ("cartesianX", "cartesianY", "cartesianZ")
SPHERICAL_FIELDS = ("sphericalRange", "sphericalAzimuth", "sphericalElevation")
TIME_FIELD = "timeStamp"
TIME_INVALID_FIELD = "isTimeStampInvalid"

Coordinates = NDArray[np.float64]


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
    headers, counts, fields = _checked_headers(reader, max_points)
    with_intensity = all("intensity" in present for present in fields)
    with_times = all(TIME_FIELD in present for present in fields)
    # A chunk of one scan at a time, copied into its place in the output: no scan is ever held
    # whole beside the output.
    points = np.empty((sum(counts), 3), dtype=np.float64)
    intensity: NDArray | None = None
    station = np.empty(sum(counts), dtype=np.int32)
    times = np.empty(sum(counts)) if with_times else None
    origins: list[NDArray[np.float64]] = []
    n_filled = 0
    for xyz, values, scan_times, origin, first in _scans(
        reader, headers, counts, with_intensity, with_times
    ):
        if n_filled + len(xyz) > len(points):
            raise PointCloudError(
                f"malformed E57 file: its scans hold more points than their headers declare "
                f"({sum(counts):,})"
            )
        if first:
            origins.append(origin)
        rows = slice(n_filled, n_filled + len(xyz))
        points[rows] = xyz
        station[rows] = len(origins) - 1
        if values is not None:
            if intensity is None:
                intensity = np.empty(len(points), dtype=values.dtype)
            intensity[rows] = values
        if times is not None and scan_times is not None:
            times[rows] = scan_times
        else:  # a kept point's time is flagged invalid: no times at all
            times = None
        n_filled += len(xyz)
    if not origins:
        raise PointCloudError(
            f"the E57 file holds no points: its {len(headers)} scan(s) are empty or every point "
            "is flagged invalid"
        )
    attributes: dict[str, NDArray] = {"station_index": _kept(station, n_filled)}
    if intensity is not None:
        attributes["intensity"] = _kept(intensity, n_filled)
    if times is not None:
        attributes[TIME_FIELD] = _kept(times, n_filled)
    origin_array = np.vstack(origins)
    return RawCloud(
        _kept(points, n_filled),
        attributes,
        origin_array[0] if len(origins) == 1 else origin_array,
    )


def _checked_headers(reader, max_points: int | None) -> tuple[list, list[int], list[set[str]]]:
    """The scans' headers, point counts and field names, checked (see :func:`read_e57`)."""
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
    return headers, counts, fields


def scan_blocks(
    path: str | Path, max_points: int | None
) -> Iterator[tuple[NDArray[np.float64], NDArray[np.float64]]]:
    """The points of an E57 file scan by scan, :data:`SCAN_CHUNK_POINTS` at a time, in the
    file's frame (same checks as :func:`read_e57`).

    Yields
    ------
    points : ndarray, shape (k, 3), float64
        A chunk of one scan's valid points in the file's frame (scans in order).
    origin : ndarray, shape (3,)
        Where that scan's scanner stood (its pose's translation).
    """
    import pye57

    with open(path, "rb") as handle:
        head = handle.read(len(E57_SIGNATURE))
    if head != E57_SIGNATURE:
        raise PointCloudError(
            f"not an E57 file: it does not start with the signature 'ASTM-E57' (starts with "
            f"{head!r})"
        )
    try:
        reader = pye57.E57(str(path))
    except Exception as exc:  # libE57Format's E57Exception
        raise PointCloudError(f"unreadable E57 file: {_reason(exc)}") from exc
    try:
        headers, counts, _ = _checked_headers(reader, max_points)
        for xyz, _intensity, _times, origin, _first in _scans(
            reader, headers, counts, False, False
        ):
            yield xyz, origin
    finally:
        reader.close()


def declared_point_count(path: str | Path) -> int:
    """Points the scan headers of an E57 file declare (an upper bound: invalid points are
    skipped when read)."""
    import pye57

    try:
        reader = pye57.E57(str(path))
    except Exception as exc:
        raise PointCloudError(f"unreadable E57 file: {_reason(exc)}") from exc
    try:
        return sum(int(reader.get_header(i).point_count) for i in range(reader.scan_count))
    finally:
        reader.close()


def _scans(
    reader, headers: list, counts: list[int], with_intensity: bool, with_times: bool
) -> Iterator[tuple[Coordinates, NDArray | None, Coordinates | None, Coordinates, bool]]:
    """The valid points of every scan, :data:`SCAN_CHUNK_POINTS` at a time, in the file's frame.

    Yields
    ------
    points : ndarray, shape (k, 3), float64, k > 0
    intensity : ndarray, shape (k,), or None
        Without ``with_intensity``: None.
    times : ndarray, shape (k,), float64, or None
        The points' ``timeStamp``; None without ``with_times`` or when one of them is flagged
        invalid (``isTimeStampInvalid``).
    origin : ndarray, shape (3,)
        The scan's origin.
    first : bool
        Whether this is the scan's first chunk with points (a scan whose every point is
        invalid yields nothing).
    """
    for index, header in enumerate(headers):
        if counts[index] == 0:
            continue
        try:
            origin = _scan_origin(header)
            first = True
            chunks = _scan_chunks(reader, header, counts[index], with_intensity, with_times)
            for xyz, intensity, times in chunks:
                if len(xyz):
                    yield xyz, intensity, times, origin, first
                    first = False
        except PointCloudError:
            raise
        except Exception as exc:
            raise PointCloudError(f"cannot read E57 scan {index}: {_reason(exc)}") from exc


def _scan_chunks(
    reader, header, n_points: int, with_intensity: bool, with_times: bool
) -> Iterator[tuple[NDArray[np.float64], NDArray | None, NDArray[np.float64] | None]]:
    """One scan's valid points (with intensity and times) a chunk at a time, as
    ``pye57.E57.read_scan`` gives them whole: invalid points dropped, spherical coordinates
    converted, the pose applied. ``read_scan`` does not read ``timeStamp``: libE57Format's own
    buffers read every field here, the times with them (None for a chunk where a kept point's
    time is flagged invalid)."""
    import pye57
    from pye57 import libe57

    systems = pye57.e57.COORDINATE_SYSTEMS
    spherical = header.get_coordinate_system(systems) is systems.SPHERICAL
    names = list(SPHERICAL_FIELDS if spherical else CARTESIAN_FIELDS)
    invalid_name = "sphericalInvalidState" if spherical else "cartesianInvalidState"
    present = set(header.point_fields)
    fields = [*names, *(["intensity"] if with_intensity else [])]
    fields += [name for name in (invalid_name,) if name in present]
    if with_times:
        fields += [name for name in (TIME_FIELD, TIME_INVALID_FIELD) if name in present]
    capacity = max(1, min(SCAN_CHUNK_POINTS, n_points))
    types = {**pye57.e57.SUPPORTED_POINT_FIELDS, TIME_FIELD: "d", TIME_INVALID_FIELD: "b"}
    data = {name: np.empty(capacity, dtype=types[name]) for name in fields}
    buffers = libe57.VectorSourceDestBuffer()
    for name in fields:
        buffers.append(
            libe57.SourceDestBuffer(reader.image_file, name, data[name], capacity, True, True)
        )
    vector_reader = header.points.reader(buffers)
    try:
        while (count := int(vector_reader.read())) > 0:
            valid = (
                ~data[invalid_name][:count].astype(bool)
                if invalid_name in data
                else np.ones(count, dtype=bool)
            )
            xyz = np.column_stack([data[name][:count] for name in names])[valid]
            if spherical:
                xyz = pye57.e57.convert_spherical_to_cartesian(xyz)
            if header.has_pose():
                xyz = reader.to_global(xyz, header.rotation, header.translation)
            intensity = data["intensity"][:count][valid] if with_intensity else None
            times = None
            if with_times:
                flagged = (
                    TIME_INVALID_FIELD in data
                    and (data[TIME_INVALID_FIELD][:count][valid] != 0).any()
                )
                times = None if flagged else data[TIME_FIELD][:count][valid].copy()
            yield np.asarray(xyz, dtype=np.float64), intensity, times
    finally:
        vector_reader.close()


def _kept(array: NDArray, n_rows: int) -> NDArray:
    """The first ``n_rows`` of ``array``: the array itself when full, else a trimmed copy."""
    return array if n_rows == len(array) else array[:n_rows].copy()


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
