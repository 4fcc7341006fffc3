"""Trajectory files: TUM, KITTI poses and CSV with a header, detected by their content.

* **TUM** (``timestamp tx ty tz qx qy qz qw``, one pose a line, ``#`` comments);
* **KITTI poses** (12 numbers a line: the row-major 3x4 matrix ``[R | t]`` of each pose), whose
  times come separately: a times file (one time a line, KITTI's ``times.txt``) or a constant
  rate in poses a second; without either the poses carry no times (``has_times`` False: enough
  for a cloud without per-point times, whose points take their nearest visible pose);
* **CSV with a header** (``time,x,y,z[,qx,qy,qz,qw]``; names case-insensitive, ``timestamp``,
  ``t``, ``tx``, ``position_x``, ``orientation_w``... accepted; commas, semicolons or tabs).

Every problem is a :class:`~app.core.trajectory.TrajectoryError` saying what to fix.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from app.core.trajectory import Trajectory, TrajectoryError

__all__ = ["TRAJECTORY_FORMATS", "detect_trajectory_format", "read_times", "read_trajectory"]

TRAJECTORY_FORMATS = ("tum", "kitti", "csv")
ACCEPTED = (
    "TUM ('timestamp tx ty tz qx qy qz qw' a line), KITTI poses (12 numbers a line: a 3x4 "
    "matrix, with a times file or a rate) or CSV with a header ('time,x,y,z[,qx,qy,qz,qw]')"
)
MAX_BYTES = 256 * 1024 * 1024
"""A trajectory file larger than this is refused (a million poses take ~80 MB of TUM text)."""
ROTATION_TOLERANCE = 1e-3
"""How far a KITTI rotation block may be from orthonormal (R R^T - I, largest entry)."""
COLUMN_ALIASES = {
    "time": ("time", "timestamp", "t", "stamp", "times", "time_s", "sec", "seconds"),
    "x": ("x", "tx", "pos_x", "position_x", "p_x", "px"),
    "y": ("y", "ty", "pos_y", "position_y", "p_y", "py"),
    "z": ("z", "tz", "pos_z", "position_z", "p_z", "pz"),
    "qx": ("qx", "q_x", "orientation_x", "rot_x", "quat_x"),
    "qy": ("qy", "q_y", "orientation_y", "rot_y", "quat_y"),
    "qz": ("qz", "q_z", "orientation_z", "rot_z", "quat_z"),
    "qw": ("qw", "q_w", "orientation_w", "rot_w", "quat_w"),
}

Source = bytes | str | os.PathLike


def _text(source: Source, what: str) -> str:
    """The source's text (a path's content or the bytes given), checked for size and ASCII."""
    if isinstance(source, bytes | bytearray | memoryview):
        raw = bytes(source)
    else:
        path = Path(source)
        if path.stat().st_size > MAX_BYTES:
            raise TrajectoryError(f"the {what} is larger than {MAX_BYTES // 2**20} MB")
        raw = path.read_bytes()
    if len(raw) > MAX_BYTES:
        raise TrajectoryError(f"the {what} is larger than {MAX_BYTES // 2**20} MB")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise TrajectoryError(
            f"the {what} is not text (byte {exc.start} is not UTF-8): expected {ACCEPTED}"
        ) from exc


def _data_lines(text: str) -> list[tuple[int, str]]:
    """Non-empty lines that are not ``#`` comments, with their 1-based line numbers."""
    return [
        (number, line.strip())
        for number, line in enumerate(text.splitlines(), start=1)
        if line.strip() and not line.lstrip().startswith("#")
    ]


def _numbers(line: str) -> list[float] | None:
    """The line's whitespace/comma separated numbers, or None when one is not a number."""
    try:
        return [float(value) for value in re.split(r"[\s,;]+", line.strip()) if value]
    except ValueError:
        return None


def detect_trajectory_format(text: str, filename: str | None = None) -> str:
    """``"tum"``, ``"kitti"`` or ``"csv"`` from the first data line (and the file's extension).

    Raises
    ------
    TrajectoryError
        None of them: the message names the accepted formats.
    """
    lines = _data_lines(text)
    if not lines:
        raise TrajectoryError(f"the trajectory file holds no poses: expected {ACCEPTED}")
    first = lines[0][1]
    values = _numbers(first)
    if values is None:
        if re.search(r"[A-Za-z]", first) and re.search(r"[,;\t]", first):
            return "csv"
        raise TrajectoryError(
            f"unknown trajectory format (line {lines[0][0]}: {first[:60]!r}): expected {ACCEPTED}"
        )
    suffix = Path(filename).suffix.lower() if filename else ""
    if len(values) == 8 and suffix != ".csv":
        return "tum"
    if len(values) == 12:
        return "kitti"
    raise TrajectoryError(
        f"unknown trajectory format: line {lines[0][0]} has {len(values)} numbers (a CSV "
        f"trajectory needs a header line): expected {ACCEPTED}"
    )


def read_trajectory(
    source: Source,
    *,
    filename: str | None = None,
    format: str | None = None,
    times: Source | NDArray | None = None,
    rate: float | None = None,
) -> Trajectory:
    """Read a trajectory file.

    Parameters
    ----------
    source : bytes, str or os.PathLike
        The file's content or its path.
    filename : str, optional
        Its name (the extension helps detection; messages use it).
    format : {"tum", "kitti", "csv"}, optional
        Default: :func:`detect_trajectory_format`.
    times : bytes, path or ndarray, shape (m,), optional
        KITTI poses' times: a times file (one time a line) or the array.
    rate : float, optional
        KITTI poses' constant rate (poses a second): pose i at ``i / rate`` seconds.

    Returns
    -------
    Trajectory

    Raises
    ------
    TrajectoryError
        Unknown format, malformed lines, non-finite values, non-unit quaternions, a rotation
        that is not one, times unsorted or repeated, times given in a way that does not fit.
    """
    label = filename or (None if isinstance(source, bytes | bytearray) else str(source))
    prefix = f"{Path(label).name}: " if label else ""
    try:
        text = _text(source, "trajectory file")
        chosen = (format or "").lower().lstrip(".") or detect_trajectory_format(text, label)
        if chosen not in TRAJECTORY_FORMATS:
            raise TrajectoryError(f"unknown trajectory format {format!r}: expected {ACCEPTED}")
        if chosen != "kitti" and (times is not None or rate is not None):
            raise TrajectoryError(
                f"a {chosen.upper()} trajectory has its own times: times files and rates are "
                "only for KITTI poses"
            )
        if chosen == "tum":
            return _read_tum(text)
        if chosen == "csv":
            return _read_csv(text)
        return _read_kitti(text, times, rate)
    except TrajectoryError as exc:
        raise TrajectoryError(f"{prefix}{exc}") from exc


def _table(lines: list[tuple[int, str]], width: int, what: str) -> NDArray[np.float64]:
    """The lines' numbers as an (m, width) array; a line of another width is named."""
    rows = []
    for number, line in lines:
        values = _numbers(line)
        if values is None or len(values) != width:
            found = "a non-number" if values is None else f"{len(values)} numbers"
            raise TrajectoryError(
                f"line {number} of the {what} has {found} where {width} numbers are expected"
            )
        rows.append(values)
    table = np.asarray(rows, dtype=np.float64).reshape(-1, width)
    bad = ~np.isfinite(table).all(axis=1)
    if bad.any():
        raise TrajectoryError(
            f"line {lines[int(np.argmax(bad))][0]} of the {what} has a non-finite value "
            "(nan or inf): every time, position and quaternion must be finite"
        )
    return table


def _checked_times(times: NDArray[np.float64], lines: list[int], what: str) -> None:
    """Raise unless the times increase strictly, naming the first line where they do not."""
    steps = np.diff(times)
    if (steps <= 0).any():
        first = int(np.argmax(steps <= 0)) + 1
        kind = "repeats" if steps[first - 1] == 0 else "goes back from"
        raise TrajectoryError(
            f"the {what}'s times must increase strictly: line {lines[first]} {kind} the "
            f"previous pose's time ({times[first]!r} after {times[first - 1]!r}); sort the "
            "poses by time and drop duplicates"
        )


def _checked_quaternions(quaternions: NDArray[np.float64], lines: list[int]) -> None:
    norms = np.linalg.norm(quaternions, axis=1)
    off = np.abs(norms - 1.0) > 1e-3
    if off.any():
        first = int(np.argmax(off))
        raise TrajectoryError(
            f"line {lines[first]}: the quaternion (qx, qy, qz, qw) has norm {norms[first]:.6g}, "
            "not 1: give unit quaternions"
        )


def _read_tum(text: str) -> Trajectory:
    lines = _data_lines(text)
    table = _table(lines, 8, "TUM trajectory")
    numbers = [number for number, _ in lines]
    _checked_times(table[:, 0], numbers, "TUM trajectory")
    _checked_quaternions(table[:, 4:8], numbers)
    return Trajectory(table[:, 0], table[:, 1:4], table[:, 4:8])


def _column_of(names: list[str]) -> dict[str, int]:
    """Which header column holds each of time, x, y, z, qx, qy, qz, qw (case-insensitive)."""
    normalised = [
        re.sub(r"\s*[\[(].*$", "", name.strip().lstrip("#").strip()).lower() for name in names
    ]
    found: dict[str, int] = {}
    for key, aliases in COLUMN_ALIASES.items():
        for column, name in enumerate(normalised):
            if name in aliases or name.replace("-", "_").replace(".", "_") in aliases:
                found[key] = column
                break
    return found


def _read_csv(text: str) -> Trajectory:
    lines = _data_lines(text)
    header_number, header = lines[0]
    delimiter = next((d for d in (",", ";", "\t") if d in header), ",")
    names = header.split(delimiter)
    columns = _column_of(names)
    missing = [key for key in ("time", "x", "y", "z") if key not in columns]
    if missing:
        raise TrajectoryError(
            f"the CSV trajectory's header (line {header_number}: {header[:80]!r}) has no "
            f"{', '.join(missing)} column: name the columns time,x,y,z[,qx,qy,qz,qw]"
        )
    quaternion_keys = ("qx", "qy", "qz", "qw")
    with_quaternion = [key in columns for key in quaternion_keys]
    if any(with_quaternion) and not all(with_quaternion):
        raise TrajectoryError(
            "the CSV trajectory has only some quaternion columns: give all of qx,qy,qz,qw or none"
        )
    body = lines[1:]
    if not body:
        raise TrajectoryError("the CSV trajectory has a header but no poses")
    rows = []
    for number, line in body:
        cells = line.split(delimiter)
        if len(cells) != len(names):
            raise TrajectoryError(
                f"line {number} of the CSV trajectory has {len(cells)} columns where the header "
                f"has {len(names)}"
            )
        try:
            rows.append([float(cells[columns[key]]) for key in columns])
        except ValueError as exc:
            raise TrajectoryError(f"line {number} of the CSV trajectory: {exc}") from exc
    keys = list(columns)
    table = np.asarray(rows, dtype=np.float64)
    bad = ~np.isfinite(table).all(axis=1)
    if bad.any():
        raise TrajectoryError(
            f"line {body[int(np.argmax(bad))][0]} of the CSV trajectory has a non-finite value "
            "(nan or inf): every time, position and quaternion must be finite"
        )
    numbers = [number for number, _ in body]
    times = table[:, keys.index("time")]
    _checked_times(times, numbers, "CSV trajectory")
    positions = table[:, [keys.index(key) for key in ("x", "y", "z")]]
    orientations = None
    if all(with_quaternion):
        orientations = table[:, [keys.index(key) for key in quaternion_keys]]
        _checked_quaternions(orientations, numbers)
    return Trajectory(times, positions, orientations)


def read_times(source: Source | NDArray, count: int) -> NDArray[np.float64]:
    """KITTI poses' times: a times file (one a line, ``#`` comments) or an array; ``count`` of them.

    Raises
    ------
    TrajectoryError
        Not one finite time a pose, or not strictly increasing.
    """
    if isinstance(source, np.ndarray):
        times = np.asarray(source, dtype=np.float64).reshape(-1)
        numbers = list(range(1, times.shape[0] + 1))
        if not np.isfinite(times).all():
            raise TrajectoryError("the pose times have a non-finite value: give finite times")
    else:
        lines = _data_lines(_text(source, "times file"))
        times = _table(lines, 1, "times file")[:, 0]
        numbers = [number for number, _ in lines]
    if times.shape[0] != count:
        raise TrajectoryError(
            f"the times file has {times.shape[0]} times for {count} KITTI poses: give one time "
            "a pose"
        )
    _checked_times(times, numbers, "times file")
    return times


def _read_kitti(text: str, times: Source | NDArray | None, rate: float | None) -> Trajectory:
    lines = _data_lines(text)
    table = _table(lines, 12, "KITTI poses file")
    matrices = table.reshape(-1, 3, 4)
    rotations = matrices[:, :, :3]
    error = np.abs(rotations @ rotations.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
    determinant = np.linalg.det(rotations)
    bad = (error > ROTATION_TOLERANCE) | (determinant < 0)
    if bad.any():
        first = int(np.argmax(bad))
        raise TrajectoryError(
            f"line {lines[first][0]} of the KITTI poses file: its 3x3 block is not a rotation "
            f"(orthonormality error {error[first]:.3g}, determinant {determinant[first]:.3g}): "
            "give rigid poses [R | t]"
        )
    from scipy.spatial.transform import Rotation  # here: reading a point file needs no scipy

    orientations = Rotation.from_matrix(rotations).as_quat()  # (qx, qy, qz, qw)
    positions = matrices[:, :, 3]
    count = positions.shape[0]
    if times is not None and rate is not None:
        raise TrajectoryError("give KITTI poses either a times file or a rate, not both")
    has_times = True
    if times is not None:
        pose_times = read_times(times, count)
    elif rate is not None:
        if not (math.isfinite(rate) and rate > 0):
            raise TrajectoryError(f"the KITTI pose rate must be a positive number, got {rate!r}")
        pose_times = np.arange(count, dtype=np.float64) / float(rate)
    else:  # the pose order stands for the times: positions only (see has_times)
        pose_times = np.arange(count, dtype=np.float64)
        has_times = False
    return Trajectory(pose_times, positions, orientations, has_times=has_times)


POINT_TIME_FIELDS = ("time", "gps_time", "timestamp", "timeStamp", "t")
"""Per-point time fields, first found wins (case-insensitive): PLY/PCD ``time``, ``timestamp``,
``t``; LAS/LAZ ``gps_time``; E57 ``timeStamp``."""


def with_point_times(attributes: dict[str, NDArray]) -> dict[str, NDArray]:
    """``attributes`` with the per-point times, if any, also under ``"time"`` as float64.

    The first of :data:`POINT_TIME_FIELDS` present (case-insensitive) is used; a float64 field
    is shared, not copied.  Attributes without times are returned unchanged.
    """
    by_lower = {name.lower(): name for name in attributes}
    for candidate in POINT_TIME_FIELDS:
        name = by_lower.get(candidate.lower())
        values = None if name is None else np.asarray(attributes[name])
        if values is not None and values.ndim == 1 and values.dtype.kind in "iuf":
            return {**attributes, "time": values.astype(np.float64, copy=False)}
    return attributes
