"""The point cloud container used throughout the core.

A :class:`PointCloud` holds finite float64 coordinates together with the bookkeeping needed to
map per-point results back to the rows of the file it was read from (points with NaN/inf
coordinates are dropped on load but keep their place in exported labels).

Georeferenced data (e.g. UTM coordinates, x ~ 5e5, y ~ 5e6) loses precision in float32 and in
covariance sums; :func:`choose_local_origin` gives a rounded origin that callers subtract before
numeric work and add back when reporting coordinates.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from app.core.errors import PointCloudError

MIN_POINTS = 10
"""Fewest finite points a cloud may have: below this no detector or registration is meaningful."""


@dataclass(frozen=True, eq=False)
class PointCloud:
    """Finite 3D points plus optional per-point attributes.

    Attributes
    ----------
    points : ndarray, shape (n, 3), float64
        Finite coordinates, in the file's frame and units.
    source_index : ndarray, shape (n,), int64
        Row of each point in the source (file order); strictly increasing.
    n_source : int
        Number of rows in the source, including dropped non-finite rows.
    attributes : mapping of str to ndarray, each shape (n, ...)
        Extra per-point fields kept from the file (intensity, rgb, normals, ...).
    sensor_origin : ndarray, shape (3,), float64, or None
        Where the sensor was when the scan was taken, in the same frame as ``points``, when
        known (a PCD ``VIEWPOINT``, a synthetic scene, or given by the caller).
    """

    points: NDArray[np.float64]
    source_index: NDArray[np.int64]
    n_source: int
    attributes: Mapping[str, NDArray] = field(default_factory=dict)
    sensor_origin: NDArray[np.float64] | None = None

    @classmethod
    def from_array(
        cls,
        points: NDArray,
        attributes: Mapping[str, NDArray] | None = None,
        sensor_origin: NDArray | None = None,
        min_points: int = MIN_POINTS,
    ) -> PointCloud:
        """Validate raw coordinates, drop non-finite rows and build a cloud.

        Parameters
        ----------
        points : array_like, shape (n, 3)
            Coordinates in file order; converted to float64.
        attributes : mapping of str to array_like, each shape (n, ...), optional
            Per-point fields in the same order; rows are dropped together with the points.
        sensor_origin : array_like, shape (3,), optional
            Sensor position in the same frame.
        min_points : int
            Raise :class:`PointCloudError` when fewer finite points remain.

        Raises
        ------
        PointCloudError
            Wrong shape, no finite points, or fewer than ``min_points`` finite points.
        """
        array = np.asarray(points)
        if array.ndim != 2 or array.shape[1] != 3:
            raise PointCloudError(
                f"points must have shape (n, 3), got {array.shape}; give x, y, z per point"
            )
        try:
            array = array.astype(np.float64, copy=False)
        except (TypeError, ValueError) as exc:
            raise PointCloudError(f"coordinates are not numbers: {exc}") from exc
        n_source = int(array.shape[0])
        if n_source == 0:
            raise PointCloudError("the point cloud is empty (0 points)")
        # Fast path: one flat reduction (~20x cheaper than the per-row test) when all is finite.
        if np.isfinite(array).all():
            finite = None
            n_finite = n_source
        else:
            finite = np.isfinite(array).all(axis=1)
            n_finite = int(finite.sum())
        if n_finite == 0:
            raise PointCloudError(
                f"none of the {n_source} points has finite coordinates (all contain NaN or inf)"
            )
        if n_finite < min_points:
            raise PointCloudError(
                f"only {n_finite} finite points (of {n_source}); at least {min_points} are needed"
            )
        kept_attributes: dict[str, NDArray] = {}
        for name, values in (attributes or {}).items():
            values = np.asarray(values)
            if values.shape[:1] != (n_source,):
                raise PointCloudError(
                    f"attribute {name!r} has {values.shape[0] if values.ndim else 0} rows, "
                    f"expected {n_source} (one per point)"
                )
            kept_attributes[name] = values if n_finite == n_source else values[finite]
        origin = None
        if sensor_origin is not None:
            origin = np.asarray(sensor_origin, dtype=np.float64).reshape(3)
            if not np.isfinite(origin).all():
                raise PointCloudError(f"sensor origin {origin.tolist()} is not finite")
        if n_finite == n_source:
            kept_points = np.ascontiguousarray(array)
            source_index = np.arange(n_source, dtype=np.int64)
        else:
            kept_points = np.ascontiguousarray(array[finite])
            source_index = np.flatnonzero(finite).astype(np.int64)
        return cls(kept_points, source_index, n_source, kept_attributes, origin)

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
        return values[self.source_index]

    def bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Axis-aligned bounding box ``(min, max)``, each shape (3,)."""
        return self.points.min(axis=0), self.points.max(axis=0)


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
    low = points.min(axis=0)
    high = points.max(axis=0)
    centre = (low + high) / 2.0
    if np.all(np.abs(centre) < 1000.0):
        return np.zeros(3)
    return np.round(centre / quantum) * quantum


def voxel_downsample_indices(points: NDArray[np.float64], voxel_size: float) -> NDArray[np.int64]:
    """Indices of one point per occupied voxel (the first in input order).

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    voxel_size : float
        Edge length of the cubic voxels, > 0.

    Returns
    -------
    ndarray, shape (k,), int64
        Sorted indices into ``points``; k <= n.
    """
    if voxel_size <= 0:
        raise ValueError("voxel_size must be positive")
    keys = np.floor((points - points.min(axis=0)) / voxel_size).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return np.sort(first).astype(np.int64)
