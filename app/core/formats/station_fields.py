"""Per-point station fields of any format, turned into a station index and station origins.

A cloud merged from several scanner stations may say which station took each point, as extra
per-point fields (PLY properties, LAS extra-bytes dimensions, PCD fields, NPY/NPZ fields, text
columns with a header):

- a station index: ``station_index``, ``station`` or ``scan_index`` (whole numbers >= 0,
  case-insensitive names; the first present in that order is used), kept as the
  ``station_index`` attribute; the origins then come from elsewhere (the upload's
  ``sensor_origin`` list, ``--sensor-origin``/``--scan-origin``, compare parameters), in the
  order of the indices;
- a per-point origin: ``origin_x``, ``origin_y``, ``origin_z`` (where the sensor stood when it
  took the point, in the file's frame): its distinct positions become the cloud's
  ``sensor_origin`` ((k, 3), or (3,) for one) and the ``station_index`` says which one took
  each point. A per-point origin wins over a station index and over a PCD ``VIEWPOINT``.

E57 files carry both already (:mod:`app.core.formats.e57`).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from numpy.typing import NDArray

from app.core.errors import PointCloudError
from app.core.formats._common import RawCloud

STATION_INDEX_NAMES = ("station_index", "station", "scan_index")
"""Field names read as a per-point station index (case-insensitive), in order of preference."""
ORIGIN_NAMES = ("origin_x", "origin_y", "origin_z")
"""Field names read as a per-point sensor origin (case-insensitive)."""
MAX_STATIONS = 1024
"""Most distinct per-point origins accepted (more is a trajectory, not a set of stations)."""


def has_station_fields(names: Iterable[str]) -> bool:
    """Whether any of the field ``names`` is a station index or a per-point origin field."""
    return bool({name.lower() for name in names} & {*STATION_INDEX_NAMES, *ORIGIN_NAMES})


def with_station_fields(raw: RawCloud) -> RawCloud:
    """``raw`` with its station fields read: ``station_index`` (int32) and ``sensor_origin``.

    Returns
    -------
    RawCloud
        The same cloud; the per-point origin fields, when present, replaced by
        ``sensor_origin`` (shape (3,) or (k, 3)) and ``station_index`` (n,) int32; a station
        index field under another accepted name renamed ``station_index``.

    Raises
    ------
    PointCloudError
        A station index that is not whole numbers >= 0; per-point origins not finite where the
        point is, only some of the three origin fields, or more than :data:`MAX_STATIONS`
        distinct origins.
    """
    by_lower = {name.lower(): name for name in raw.attributes}
    origin_names = [by_lower.get(name) for name in ORIGIN_NAMES]
    if any(origin_names):
        return _from_origins(raw, origin_names)
    found = next((by_lower[name] for name in STATION_INDEX_NAMES if name in by_lower), None)
    if found is None:
        return raw
    attributes = dict(raw.attributes)
    attributes["station_index"] = _checked_index(attributes.pop(found), found)
    return RawCloud(raw.points, attributes, raw.sensor_origin)


def _checked_index(values: NDArray, name: str) -> NDArray[np.int32]:
    """A station index field as int32, shape (n,)."""
    array = np.asarray(values)
    if array.ndim != 1 or array.dtype.kind not in "iufb":
        raise PointCloudError(
            f"the station index field {name!r} must be one whole number per point, got "
            f"{array.dtype} values of shape {array.shape}"
        )
    if array.dtype.kind == "f" and (
        not np.isfinite(array).all() or (array != np.round(array)).any()
    ):
        raise PointCloudError(
            f"the station index field {name!r} must hold whole numbers 0, 1, ... (which station "
            "took each point)"
        )
    if array.size and (array.min() < 0 or array.max() >= np.iinfo(np.int32).max):
        raise PointCloudError(
            f"the station index field {name!r} holds {array.min()} .. {array.max()}; station "
            "indices count from 0"
        )
    return array.astype(np.int32)


def _from_origins(raw: RawCloud, names: list[str | None]) -> RawCloud:
    """Station origins and index from the per-point origin fields ``names``."""
    if not all(names):
        missing = [wanted for wanted, name in zip(ORIGIN_NAMES, names, strict=True) if not name]
        raise PointCloudError(
            f"per-point sensor origins need the three fields {', '.join(ORIGIN_NAMES)}; "
            f"{', '.join(missing)} missing"
        )
    attributes = dict(raw.attributes)
    origins = np.column_stack(
        [np.asarray(attributes.pop(name), dtype=np.float64) for name in names if name]
    )
    finite_points = np.isfinite(np.asarray(raw.points, dtype=np.float64)).all(axis=1)
    bad = finite_points & ~np.isfinite(origins).all(axis=1)
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise PointCloudError(
            f"per-point sensor origin of row {row} is {origins[row].tolist()}: every point needs "
            "a finite origin_x, origin_y, origin_z"
        )
    origins[~finite_points] = origins[finite_points][0] if finite_points.any() else 0.0
    distinct, station = np.unique(origins, axis=0, return_inverse=True)
    if len(distinct) > MAX_STATIONS:
        raise PointCloudError(
            f"the per-point sensor origins name {len(distinct):,} different positions; at most "
            f"{MAX_STATIONS:,} stations are supported (give each station's points the same "
            "origin)"
        )
    # number the stations in the order of their first point, as the file lists them
    first_row = np.full(len(distinct), len(origins), dtype=np.int64)
    np.minimum.at(first_row, station.reshape(-1), np.arange(len(origins)))
    order = np.argsort(first_row, kind="stable")
    renumber = np.empty_like(order)
    renumber[order] = np.arange(len(order))
    attributes["station_index"] = renumber[station.reshape(-1)].astype(np.int32)
    stations = distinct[order]
    return RawCloud(raw.points, attributes, stations[0] if len(stations) == 1 else stations)
