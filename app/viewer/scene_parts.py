"""Parts of a job's scene beside its layers: the drawn points per scan, the candidate pools of
live relabelling, the sensor markers, and the checks of labels and distances (used by
:mod:`app.viewer.scene`)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.labels import LABEL_CHANGED, LABEL_UNOBSERVED
from app.core.registration import apply_transform

SIDES = ("reference", "scan")


@dataclass(frozen=True, eq=False)
class SideCloud:
    """The drawn points of one scan (after downsampling), with what the job said of each.

    ``points`` (k, 3) float32 local; ``labels`` (k,) int8 (1 changed, 0 unchanged, -1
    unobserved); ``distances`` (k,) float32, unsigned distance to the other scan's surface (NaN
    when unknown); ``indices`` (k,) int64 rows of the side's full cloud.
    """

    side: str
    points: NDArray[np.float32]
    labels: NDArray[np.int8]
    distances: NDArray[np.float32]
    indices: NDArray[np.int64]

    @property
    def signed_distances(self) -> NDArray[np.float32]:
        """Distances signed by side: reference (material gone) negative, scan positive."""
        return -self.distances if self.side == "reference" else self.distances


@dataclass(frozen=True, eq=False)
class CandidatePool:
    """The points of one scan that a looser distance threshold could make changed.

    Observed points whose distance is at least ``floor`` (metres), in the full cloud (not
    downsampled): ``points`` (p, 3) float64 local, ``distances`` (p,), ``indices`` (p,) rows.
    Relabelling live only clusters these (:mod:`app.viewer.regions_display`).  The floor is
    half the job's threshold; only the farthest :data:`MAX_POOL_POINTS` are kept.
    """

    side: str
    floor: float
    points: NDArray[np.float64]
    distances: NDArray[np.float32]
    indices: NDArray[np.int64]
    changed: NDArray[np.bool_]
    """(p,) whether the job labelled the point changed (it passed every test of the worker)."""
    spacing: NDArray[np.float64]
    """(p,) local point spacing in the full cloud, as the localiser estimates it."""


@dataclass(frozen=True)
class SensorMarker:
    """Where a scanner stood (reference frame, local coordinates), as the job reports it."""

    side: str
    position_local: tuple[float, float, float]
    position: tuple[float, float, float]
    source: str
    confidence: float | None


POOL_FLOOR_FRACTION = 0.5
"""The live distance slider goes down to this fraction of the job's change threshold."""

MAX_POOL_POINTS = 300_000
"""Most candidate points per scan kept for live relabelling (the farthest first)."""


def candidate_pool(
    side: str,
    points: NDArray[np.float64],
    labels: NDArray[np.int8],
    distances: NDArray[np.floating],
    origin: NDArray[np.float64],
    change_threshold: float | None,
) -> CandidatePool:
    """The observed points of one scan at least ``0.5 x change_threshold`` from the other."""
    floor = POOL_FLOOR_FRACTION * change_threshold if change_threshold else 0.0
    with np.errstate(invalid="ignore"):
        rows = np.flatnonzero((labels != LABEL_UNOBSERVED) & (distances >= floor))
    if change_threshold is None:
        rows = rows[:0]
    if len(rows) > MAX_POOL_POINTS:
        farthest = np.argsort(-distances[rows], kind="stable")[:MAX_POOL_POINTS]
        rows = np.sort(rows[farthest])
        floor = float(distances[rows].min())
    return CandidatePool(
        side=side,
        floor=float(floor),
        points=points[rows] - origin,
        distances=distances[rows].astype(np.float32),
        indices=rows.astype(np.int64),
        changed=labels[rows] == LABEL_CHANGED,
        spacing=local_spacing(points, rows),
    )


SPACING_NEIGHBOURS = 10
"""The localiser's neighbourhood size (``n_neighbors``): spacing from the 10th neighbour."""


def local_spacing(points: NDArray[np.float64], rows: NDArray[np.int64]) -> NDArray[np.float64]:
    """Spacing at ``points[rows]``: the 10th neighbour's distance x sqrt(pi / 10), as the
    localiser's :func:`~app.core.localise.surface.local_geometry` (before its smoothing)."""
    if len(rows) == 0 or len(points) < 2:
        return np.full(len(rows), 1.0)
    k = min(SPACING_NEIGHBOURS + 1, len(points))
    distances, _ = KDTree(points).query(points[rows], k=k)
    kth = np.asarray(distances, dtype=np.float64).reshape(len(rows), -1)[:, -1]
    return np.maximum(kth * math.sqrt(math.pi / (k - 1)), 1e-9)


def sensor_markers(
    sensor_origins: Mapping[str, Any], transform: NDArray[np.float64], origin: NDArray[np.float64]
) -> tuple[SensorMarker, ...]:
    """Markers of the sensor positions a job reports; malformed entries are skipped."""
    markers = []
    for side in SIDES:
        entries = sensor_origins.get(side) if isinstance(sensor_origins, Mapping) else None
        for entry in entries if isinstance(entries, Sequence) else ():
            if not isinstance(entry, Mapping):
                continue
            try:
                position = np.asarray(entry.get("origin"), dtype=np.float64).reshape(3)
            except (TypeError, ValueError):
                continue
            if not np.isfinite(position).all():
                continue
            if side == "scan":
                position = apply_transform(position.reshape(1, 3), transform)[0]
            confidence = entry.get("confidence")
            markers.append(
                SensorMarker(
                    side=side,
                    position_local=triple(position - origin),
                    position=triple(position),
                    source=str(entry.get("source") or "unknown"),
                    confidence=None if confidence is None else float(confidence),
                )
            )
    return tuple(markers)


def check_distances(distances: NDArray | None, n_points: int, which: str) -> NDArray[np.float32]:
    """Distances as float32 with one per point (all NaN when None)."""
    if distances is None:
        return np.full(n_points, np.nan, dtype=np.float32)
    array = np.asarray(distances, dtype=np.float32).reshape(-1)
    if array.shape[0] != n_points:
        raise ValueError(f"{which} distances: {array.shape[0]} values for {n_points} points")
    return array


def triple(values: Any) -> tuple[float, float, float]:
    """Three Python floats."""
    array = np.asarray(values, dtype=np.float64).reshape(3)
    return (float(array[0]), float(array[1]), float(array[2]))


def check_labels(labels: NDArray | None, n_points: int, which: str) -> NDArray[np.int8]:
    """Labels as int8 with one per point (all unchanged when None)."""
    if labels is None:
        return np.zeros(n_points, dtype=np.int8)
    array = np.asarray(labels).astype(np.int8, copy=False).reshape(-1)
    if array.shape[0] != n_points:
        raise ValueError(f"{which} labels: {array.shape[0]} values for {n_points} points")
    return array


def smallest_changed_distance(
    labels: Mapping[str, NDArray[np.int8]], distances: Mapping[str, NDArray]
) -> float | None:
    """The smallest finite distance of a changed point of either side (None when none)."""
    changed_distances = np.concatenate(
        [distances[side][labels[side] == LABEL_CHANGED] for side in SIDES]
    )
    changed_distances = changed_distances[np.isfinite(changed_distances)]
    return float(changed_distances.min()) if changed_distances.size else None
