"""The point cloud container used throughout the core.

A :class:`PointCloud` holds finite float64 coordinates together with the bookkeeping needed to
map per-point results back to the rows of the file it was read from (points with NaN/inf
coordinates are dropped on load but keep their place in exported labels).

Georeferenced data (e.g. UTM coordinates, x ~ 5e5, y ~ 5e6) loses precision in float32 and in
covariance sums; :func:`choose_local_origin` gives a rounded origin that callers subtract before
numeric work and add back when reporting coordinates.

Readers hand over views of their files, converted a block at a time by
:mod:`app.core.blocks`; :mod:`app.core.cloud_summary` checks and bounds coordinates with the
same rules as :meth:`PointCloud.from_array` without building the cloud.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from app.core.blocks import FileRows, float64_checked
from app.core.errors import PointCloudError
from app.core.trajectory import Trajectory

MIN_POINTS = 10
"""Fewest finite points a cloud may have: below this no detector or registration is meaningful."""


class _SourceIndex:
    """``PointCloud.source_index``: stored ``None`` (no row dropped) becomes an ``arange`` on first
    access, so loading a cloud without NaN rows does not write 8 bytes per point up front."""

    def __set_name__(self, owner: type, name: str) -> None:
        self._slot = f"_{name}"

    def __get__(self, instance: object, owner: type | None = None) -> NDArray[np.int64]:
        if instance is None:
            raise AttributeError(self._slot[1:])  # no class-level default: the field is required
        stored = instance.__dict__[self._slot]
        if stored is None:
            stored = np.arange(instance.n_source, dtype=np.int64)  # type: ignore[attr-defined]
            instance.__dict__[self._slot] = stored
        return stored

    def __set__(self, instance: object, value: NDArray[np.int64] | None) -> None:
        instance.__dict__[self._slot] = value


def _is_owned_float64(array: NDArray) -> bool:
    """Native float64, C-contiguous and writeable: usable as the cloud's points without a copy."""
    return (
        array.dtype == np.float64
        and array.dtype.isnative
        and array.flags.c_contiguous
        and array.flags.writeable
    )


def _surely_finite(values: NDArray) -> bool:
    """True only when every value of the float array ``values`` is finite (one pass, no temporary).

    ``dot(v, v)`` is NaN or inf as soon as one value is; it may also overflow to inf for huge
    finite values (|v| > ~1e154 in float64), so False means "check row by row", never "not
    finite".
    """
    flat = values.reshape(-1)
    if flat.dtype.kind != "f" or not flat.dtype.isnative or not flat.flags.c_contiguous:
        return bool(np.isfinite(values).all())
    with np.errstate(over="ignore", invalid="ignore"):
        return bool(np.isfinite(np.dot(flat, flat)))


def as_points(points: NDArray, name: str) -> NDArray[np.float64]:
    """One cloud handed to a core stage, checked: float64, shape (n, 3), finite, n >= MIN_POINTS.

    Parameters
    ----------
    points : array_like, shape (n, 3)
    name : str
        What the caller calls it (``"reference"``, ``"scan"``), for the message.

    Returns
    -------
    ndarray, shape (n, 3), float64, C-contiguous

    Raises
    ------
    PointCloudError
        Naming ``name`` and what is wrong.
    """
    try:
        array = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise PointCloudError(f"{name}: coordinates are not numbers ({exc})") from exc
    if array.ndim != 2 or array.shape[1] != 3:
        raise PointCloudError(f"{name} must have shape (n, 3), got {array.shape}")
    if array.shape[0] < MIN_POINTS:
        raise PointCloudError(
            f"{name} has {array.shape[0]} points; at least {MIN_POINTS} are needed"
        )
    if not np.isfinite(array).all():
        raise PointCloudError(f"{name} contains NaN or inf coordinates; drop those points first")
    return np.ascontiguousarray(array)


def checked_coordinates(points: NDArray) -> NDArray:
    """``points`` as an array with one row of x, y, z per point and at least one row.

    Parameters
    ----------
    points : array_like, shape (n, 3)

    Returns
    -------
    ndarray, shape (n, 3), n > 0
        ``np.asarray(points)``, its dtype unchanged.

    Raises
    ------
    PointCloudError
        Another shape, or no rows.
    """
    array = np.asarray(points)
    if array.ndim != 2 or array.shape[1] != 3:
        raise PointCloudError(
            f"points must have shape (n, 3), got {array.shape}; give x, y, z per point"
        )
    check_not_empty(int(array.shape[0]))
    return array


def check_not_empty(n_source: int) -> None:
    """Refuse a source of ``n_source`` == 0 rows with :class:`PointCloudError`."""
    if n_source == 0:
        raise PointCloudError("the point cloud is empty (0 points)")


def as_float64(array: NDArray) -> NDArray[np.float64]:
    """``array`` as float64 (no copy when it is already).

    Parameters
    ----------
    array : ndarray, shape (n, 3)

    Returns
    -------
    ndarray, shape (n, 3), float64

    Raises
    ------
    PointCloudError
        The values are not numbers.
    """
    try:
        return array.astype(np.float64, copy=False)
    except (TypeError, ValueError) as exc:
        raise PointCloudError(f"coordinates are not numbers: {exc}") from exc


def check_finite_count(n_finite: int, n_source: int, min_points: int) -> None:
    """Refuse (:class:`PointCloudError`) a cloud with no finite point, or fewer than
    ``min_points``, of ``n_source`` rows."""
    if n_finite == 0:
        raise PointCloudError(
            f"none of the {n_source} points has finite coordinates (all contain NaN or inf)"
        )
    if n_finite < min_points:
        raise PointCloudError(
            f"only {n_finite} finite points (of {n_source}); at least {min_points} are needed"
        )


def checked_attributes(
    attributes: Mapping[str, NDArray] | None, n_source: int
) -> dict[str, NDArray]:
    """The per-point fields as arrays, each with one row per source row.

    Parameters
    ----------
    attributes : mapping of str to array_like, each shape (n_source, ...), or None
    n_source : int

    Returns
    -------
    dict of str to ndarray, each shape (n_source, ...)

    Raises
    ------
    PointCloudError
        A field has another number of rows.
    """
    checked: dict[str, NDArray] = {}
    for name, values in (attributes or {}).items():
        values = np.asarray(values)
        if values.shape[:1] != (n_source,):
            raise PointCloudError(
                f"attribute {name!r} has {values.shape[0] if values.ndim else 0} rows, "
                f"expected {n_source} (one per point)"
            )
        checked[name] = values
    return checked


def checked_sensor_origin(sensor_origin: NDArray | None) -> NDArray[np.float64] | None:
    """The sensor origin(s) as a finite float64 array (None stays None).

    Parameters
    ----------
    sensor_origin : array_like, shape (3,) or (k, 3), or None
        One origin, or one per station of a cloud merged from k stations (an E57 file's
        scans, per-point origin fields).

    Returns
    -------
    ndarray, shape (3,) or (k, 3), float64, or None

    Raises
    ------
    PointCloudError
        A coordinate is NaN or infinite, or the shape is neither (3,) nor (k, 3).
    """
    if sensor_origin is None:
        return None
    origin = np.asarray(sensor_origin, dtype=np.float64)
    if origin.size == 3:
        origin = origin.reshape(3)
    elif origin.ndim != 2 or origin.shape[1] != 3 or origin.shape[0] == 0:
        raise PointCloudError(f"sensor origins must have shape (3,) or (k, 3), got {origin.shape}")
    if not np.isfinite(origin).all():
        raise PointCloudError(f"sensor origin {origin.tolist()} is not finite")
    return origin


@dataclass(frozen=True, eq=False)
class PointCloud:
    """Finite 3D points plus optional per-point attributes.

    Attributes
    ----------
    points : ndarray, shape (n, 3), float64
        Finite coordinates, in the file's frame and units.
    source_index : ndarray, shape (n,), int64
        Row of each point in the source (file order); strictly increasing. ``None`` given to
        the constructor means no row was dropped: the ``arange`` is then built on first use.
    n_source : int
        Number of rows in the source, including dropped non-finite rows.
    attributes : mapping of str to ndarray, each shape (n, ...)
        Extra per-point fields kept from the file (intensity, rgb, normals, ...).
    sensor_origin : ndarray, shape (3,) or (k, 3), float64, or None
        Where the sensor was when the scan was taken, in the same frame as ``points``, when
        known (a PCD ``VIEWPOINT``, a synthetic scene, or given by the caller); (k, 3) for a
        cloud merged from k stations (an E57 file's scans, per-point origin fields), whose
        ``station_index`` attribute says which station took each point.
    trajectory : Trajectory or None
        The moving sensor's path, when the cloud was taken from one (a trajectory file, a ROS
        bag); per-point times, when known, are the ``"time"`` attribute.
    sampling_points : ndarray, shape (m, 3), or None
        When ``points`` is a subsample of a larger cloud (a streamed comparison's): whole
        voxels of that cloud at full density, in the frame of ``points``, for the lidar
        sampling test (:func:`app.core.origins.sampling.lidar_sampling`) and the stations'
        search (:func:`app.core.origins.station_recovery.search_points`), which a subsample's
        thinned lattice would fail.
    """

    points: NDArray[np.float64]
    source_index: NDArray[np.int64] = _SourceIndex()  # type: ignore[assignment]
    n_source: int
    attributes: Mapping[str, NDArray] = field(default_factory=dict)
    sensor_origin: NDArray[np.float64] | None = None
    trajectory: Trajectory | None = None
    sampling_points: NDArray[np.float64] | None = None

    @classmethod
    def from_array(
        cls,
        points: NDArray,
        attributes: Mapping[str, NDArray] | None = None,
        sensor_origin: NDArray | None = None,
        min_points: int = MIN_POINTS,
        threads: int | None = None,
        file_rows: FileRows | None = None,
    ) -> PointCloud:
        """Validate raw coordinates, drop non-finite rows and build a cloud.

        Parameters
        ----------
        points : array_like, shape (n, 3)
            Coordinates in file order; converted to float64.
        attributes : mapping of str to array_like, each shape (n, ...), optional
            Per-point fields in the same order; rows are dropped together with the points.
        sensor_origin : array_like, shape (3,) or (k, 3), optional
            Sensor position(s) in the same frame.
        min_points : int
            Raise :class:`PointCloudError` when fewer finite points remain.
        threads : int, optional
            Threads that convert a large non-float64 ``points`` (e.g. a float32 view of a
            file) to float64; default :func:`~app.core.blocks.conversion_threads`. The cloud
            does not depend on it.
        file_rows : FileRows, optional
            Where ``points``, a view of a memory-mapped file, lies in that file: it is then
            read block by block from the file (faster than through the map; same cloud).

        Raises
        ------
        PointCloudError
            Wrong shape, no finite points, or fewer than ``min_points`` finite points.
        """
        array = checked_coordinates(points)
        n_source = int(array.shape[0])
        if array.dtype.kind in "iuf" and not _is_owned_float64(array):
            # Readers hand over (n, 3) views of the file (float32, big endian, padded records):
            # one pass converts them to an owned float64 array and checks finiteness on the way.
            array, all_finite = float64_checked(array, threads, file_rows)
        else:
            array = as_float64(array)
            all_finite = _surely_finite(array)
        if all_finite:
            finite = None
            n_finite = n_source
        else:
            finite = np.isfinite(array).all(axis=1)
            n_finite = int(finite.sum())
        check_finite_count(n_finite, n_source, min_points)
        kept_attributes = {
            name: values if finite is None else values[finite]
            for name, values in checked_attributes(attributes, n_source).items()
        }
        origin = checked_sensor_origin(sensor_origin)
        source_index: NDArray[np.int64] | None
        if n_finite == n_source:
            kept_points = np.ascontiguousarray(array)
            source_index = None  # every row kept: the arange is built on first use
        else:
            kept_points = np.ascontiguousarray(array[finite])
            source_index = np.flatnonzero(finite).astype(np.int64)
        return cls(kept_points, source_index, n_source, kept_attributes, origin)  # type: ignore[arg-type]

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def n_dropped(self) -> int:
        """Number of source rows dropped because a coordinate was NaN or inf."""
        return self.n_source - len(self)

    def to_source_order(self, values: NDArray, fill: object) -> NDArray:
        """Scatter per-point ``values`` (shape (n, ...)) back to file order, ``fill`` elsewhere.

        Returns
        -------
        ndarray, shape (n_source, ...)
        """
        values = np.asarray(values)
        if values.shape[:1] != (len(self),):
            raise ValueError(f"expected {len(self)} values, got {values.shape[0]}")
        out = np.full((self.n_source, *values.shape[1:]), fill, dtype=values.dtype)
        if self._all_rows_kept:
            out[...] = values
        else:
            out[self.source_index] = values
        return out

    def from_source_order(self, values: NDArray) -> NDArray:
        """The entries of per-row ``values`` (file order) that belong to this cloud's points.

        The inverse of :meth:`to_source_order`: labels saved per file row (dropped rows
        included) come back aligned with ``points``.

        Parameters
        ----------
        values : ndarray, shape (n_source, ...)

        Returns
        -------
        ndarray, shape (n, ...)

        Raises
        ------
        ValueError
            ``values`` has not one row per source row (it belongs to another file).
        """
        values = np.asarray(values)
        if values.shape[:1] != (self.n_source,):
            raise ValueError(
                f"{values.shape[0] if values.ndim else 0} values for a file of {self.n_source} "
                "rows: they belong to another file"
            )
        if self._all_rows_kept:
            return values.copy()
        return values[self.source_index]

    @property
    def _all_rows_kept(self) -> bool:
        """No row was dropped (``source_index`` is then ``arange(n_source)``, maybe not built)."""
        return self.__dict__.get("_source_index", ()) is None or self.n_source == len(self)

    def bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Axis-aligned bounding box ``(min, max)``, each shape (3,)."""
        return column_extreme(self.points, np.minimum), column_extreme(self.points, np.maximum)


EXTREME_ROWS_PER_LINE = 256
"""Rows folded into one line by :func:`column_extreme`."""


def column_extreme(points: NDArray, ufunc: np.ufunc) -> NDArray:
    """``ufunc.reduce(points, axis=0)`` (``np.minimum`` or ``np.maximum``), only faster.

    numpy reduces a C-contiguous (n, 3) array along axis 0 with a 3-element inner loop;
    folding :data:`EXTREME_ROWS_PER_LINE` rows into each line gives it a long, vectorised
    inner loop (figures in docs/performance.md). Same values, NaN propagation and errors as
    the plain reduce.

    Parameters
    ----------
    points : ndarray, shape (n, d)
    ufunc : numpy.minimum or numpy.maximum

    Returns
    -------
    ndarray, shape (d,)
    """
    points = np.asarray(points)
    rows = EXTREME_ROWS_PER_LINE
    n_folded = len(points) - len(points) % rows if points.ndim == 2 else 0
    if n_folded == 0 or not points.flags.c_contiguous:
        return ufunc.reduce(points, axis=0)
    width = points.shape[1]
    folded = ufunc.reduce(points[:n_folded].reshape(-1, rows * width), axis=0)
    extreme = ufunc.reduce(folded.reshape(rows, width), axis=0)
    if n_folded < len(points):
        extreme = ufunc(extreme, ufunc.reduce(points[n_folded:], axis=0))
    return extreme


def choose_local_origin(points: NDArray[np.float64], quantum: float = 1.0) -> NDArray[np.float64]:
    """A rounded point near the centre of ``points`` to subtract before numeric work.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    quantum : float
        The origin is a multiple of this (metres), so reported coordinates stay readable.

    Returns
    -------
    ndarray, shape (3,)
        Zero when the data is already near the origin (|centre| < 1 km), so local and file
        coordinates coincide for ordinary sensor-frame scans.
    """
    low = column_extreme(points, np.minimum)
    high = column_extreme(points, np.maximum)
    centre = (low + high) / 2.0
    if np.all(np.abs(centre) < 1000.0):
        return np.zeros(3)
    return np.round(centre / quantum) * quantum
