"""Stations known for a cloud: given origins in local coordinates, the per-point station index.

A merged survey's stations may come with it: origins given as parameters or from the file
(E57 scans, per-point origin fields), and a ``station_index`` attribute saying which station
took each point.  These helpers check and shape what is known;
:func:`~app.core.origins.station_recovery.resolve_stations` decides what is used.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.core.cloud import PointCloud
from app.core.localise.settings import as_origins, as_station_index
from app.core.localise.station_assignment import STATION_INDEX_ATTRIBUTE
from app.core.origins.estimate import estimate_origin
from app.core.origins.resolve import ResolvedOrigin

__all__ = ["estimate_each_station", "origins_in_local_frame", "station_index_of"]


def estimate_each_station(
    side: str, points: NDArray[np.float64], station: NDArray, random_state: int = 0
) -> ResolvedOrigin | None:
    """Each station's origin estimated from its own points, when every estimate is confident.

    Parameters
    ----------
    side : str
    points : ndarray, shape (n, 3)
    station : ndarray, shape (n,)
        Station index of each point (whole numbers from 0).
    random_state : int

    Returns
    -------
    ResolvedOrigin or None
        ``origin`` (k, 3) with ``source`` "estimated" and per-station confidences, when the
        index names at least two stations and each one's estimate is confident; else None.

    Raises
    ------
    InputError
        ``station`` is not one whole number >= 0 per point.
    """
    try:
        count = int(np.max(np.asarray(station))) + 1 if np.size(station) else 1
    except (TypeError, ValueError):
        count = 1  # not numbers: as_station_index says so
    index = as_station_index(station, len(points), max(count, 1), f"the {side}'s station_index")
    if index is None or index.size == 0 or index.max() < 1:
        return None
    estimates = [
        estimate_origin(points[index == number], random_state=random_state)
        for number in range(int(index.max()) + 1)
    ]
    if not all(found.confident for found in estimates):
        return None
    confidences = [round(float(found.confidence), 3) for found in estimates]
    return ResolvedOrigin(
        np.array([found.origin for found in estimates]),
        "estimated",
        min(confidences),
        station_confidence=confidences,
    )


def origins_in_local_frame(
    explicit: Any,
    from_file: NDArray[np.float64] | None,
    local_origin: NDArray[np.float64],
    name: str = "sensor origin",
) -> NDArray[np.float64] | None:
    """The sensor origins to use, shape (k, 3), shifted into local coordinates (None: unknown).

    ``explicit`` is one origin (3 numbers) or one per station ((k, 3)); it overrides the file's.
    """
    origins = as_origins(explicit, name)
    if origins is not None:
        return origins - local_origin
    if from_file is not None:
        return np.asarray(from_file, dtype=np.float64).reshape(-1, 3) - local_origin
    return None


def station_index_of(cloud: PointCloud, resolved: ResolvedOrigin, name: str) -> NDArray | None:
    """The cloud's ``station_index`` attribute, checked against origins given for it.

    Used only with given (or file) origins, whose order it refers to, or with origins estimated
    station by station from it; ignored otherwise.

    Raises
    ------
    InputError
        Not one integer per point in ``0 .. k-1`` for the k origins.
    """
    station = cloud.attributes.get(STATION_INDEX_ATTRIBUTE)
    if station is None or resolved.origin is None:
        return None
    per_station = resolved.source == "estimated" and np.asarray(resolved.origin).ndim == 2
    if resolved.source not in ("given", "file") and not per_station:
        return None
    count = np.asarray(resolved.origin).reshape(-1, 3).shape[0]
    return as_station_index(station, len(cloud), count, f"the {name}'s station_index")
