"""The 3D view of a job whose clouds are too large to load: the point budget read from the files.

:func:`app.viewer.scene.build_scene_data` takes both whole clouds. For clouds of many millions
of points the view is built from the files instead, in bounded memory:

- :func:`budget_scene` (the view a browser opens with): the job's labels (one byte a point)
  say how many points each layer has; :func:`~app.viewer.scene.allocate_budget` shares the
  point budget as for small jobs (changed points first); each layer keeps an evenly strided
  subset of its rows, chosen a chunk of labels at a time; the coordinates of only those rows
  (and of the candidates of live relabelling) are then read from the files a block at a time
  (:func:`~app.core.formats.streamed.open_point_blocks`: memory-mapped ``.npy``/PLY, LAS/LAZ
  chunks, E57 scans).
- :func:`box_scene` ("clip to a box"): every point inside an axis-aligned box of the reference
  frame at full density, up to the budget; past it the box is strided like the whole view
  (changed first) and a warning says how many points the box holds.

Memory: the labels, the chosen rows and points (bounded by the budget and the pool of live
relabelling), and one block of coordinates; the distances are read from ``details.npz`` a
chunk at a time. Rows (``SideCloud.indices``, ``CandidatePool.indices``) are file rows.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.core.formats import BagOptions
from app.core.formats.streamed import PointBlocks, open_point_blocks
from app.core.labels import LABEL_CHANGED, LABEL_UNCHANGED, LABEL_UNOBSERVED
from app.core.localise.changes import MIN_REGION_POINTS_FLOOR, MIN_REGION_POINTS_PER_SQRT
from app.core.registration import apply_transform
from app.viewer.scene import (
    DEFAULT_POINT_BUDGET,
    LAYER_STYLES,
    Layer,
    SceneData,
    allocate_budget,
    estimate_point_size,
    local_origin,
    region_boxes,
)
from app.viewer.scene_parts import (
    MAX_POOL_POINTS,
    POOL_FLOOR_FRACTION,
    CandidatePool,
    SideCloud,
    local_spacing,
    sensor_markers,
)
from app.viewer.stored_results import StoredColumn
from app.viewer.trajectory_display import trajectory_paths

CHUNK_ROWS = 1 << 22
"""Labels and distances visited per step when choosing rows (4M rows: 4-16 MB)."""

READ_BLOCK_POINTS = 1 << 20
"""Coordinates read per block from a cloud file."""

BOX_KEEP_BUDGETS = 4
"""A box holding up to this many point budgets is read once (its points kept, then strided);
a larger one is read twice (counted, then only the strided subset kept)."""

LAYER_OF: dict[tuple[str, int], str] = {
    ("reference", LABEL_UNCHANGED): "reference",
    ("scan", LABEL_UNCHANGED): "scan",
    ("reference", LABEL_CHANGED): "removed",
    ("scan", LABEL_CHANGED): "added",
    ("reference", LABEL_UNOBSERVED): "unobserved",
    ("scan", LABEL_UNOBSERVED): "unobserved",
}
"""The layer of each (side, label)."""


@dataclass(frozen=True)
class StoredSide:
    """One scan of a job as stored: its file, its labels and distances (file order)."""

    path: Path
    labels: NDArray[np.int8]
    distances: StoredColumn
    bag_options: BagOptions | None = None
    """How the job read the file when it is a ROS bag (kept beside it)."""


@dataclass(frozen=True)
class SceneContext:
    """What a job's scene shows beside its points (as :func:`build_scene_data` takes it)."""

    transform: NDArray[np.float64]
    regions: Sequence[Mapping[str, Any]] = ()
    uncertain_regions: Sequence[Mapping[str, Any]] = ()
    summary: Mapping[str, Any] | None = None
    sensor_origins: Mapping[str, Any] | None = None
    warnings: Sequence[Mapping[str, Any]] = ()
    min_region_points: int | None = None


@dataclass
class Gathered:
    """The points of one side read for the scene: file rows, reference-frame coordinates,
    labels, distances, and which of them are drawn and which are relabelling candidates."""

    rows: NDArray[np.int64]
    points: NDArray[np.float64]
    labels: NDArray[np.int8]
    distances: NDArray[np.float32]
    shown: NDArray[np.bool_]
    pool: NDArray[np.bool_]


def label_totals(sides: Mapping[str, StoredSide]) -> dict[tuple[str, int], int]:
    """Points per (side, label), counted a chunk of labels at a time (no wider copy)."""
    totals = {}
    for side, stored in sides.items():
        for label in (LABEL_UNOBSERVED, LABEL_UNCHANGED, LABEL_CHANGED):
            totals[(side, label)] = sum(
                int(np.count_nonzero(stored.labels[start : start + CHUNK_ROWS] == label))
                for start in range(0, len(stored.labels), CHUNK_ROWS)
            )
    return totals


def layer_counts(totals: Mapping[tuple[str, int], int], budget: int) -> dict[tuple[str, int], int]:
    """Points to draw per (side, label): the budget shared as for small jobs, changed first
    (the unobserved layer's share split between the sides in proportion)."""
    per_layer: dict[str, int] = {style.name: 0 for style in LAYER_STYLES}
    for key, total in totals.items():
        per_layer[LAYER_OF[key]] += total
    shown = allocate_budget(per_layer, budget)
    counts = {}
    for key, total in totals.items():
        layer = LAYER_OF[key]
        share = total / per_layer[layer] if per_layer[layer] else 0.0
        counts[key] = min(total, math.floor(shown[layer] * share))
    return counts


def strided_ranks(count: int, total: int) -> NDArray[np.int64]:
    """``count`` of ``range(total)``, evenly spaced, sorted (all when ``count >= total``)."""
    if count >= total:
        return np.arange(total, dtype=np.int64)
    return (np.arange(count, dtype=np.int64) * total) // max(count, 1)


def rows_with_label(
    labels: NDArray[np.int8], label: int, ranks: NDArray[np.int64]
) -> NDArray[np.int64]:
    """The file rows of the ``ranks``-th points labelled ``label``, a chunk at a time."""
    rows = []
    seen = 0
    for start in range(0, len(labels), CHUNK_ROWS):
        matching = np.flatnonzero(labels[start : start + CHUNK_ROWS] == label)
        low, high = np.searchsorted(ranks, [seen, seen + len(matching)])
        rows.append(start + matching[ranks[low:high] - seen])
        seen += len(matching)
    return np.concatenate(rows) if rows else np.zeros(0, np.int64)


def change_threshold_of(sides: Mapping[str, StoredSide]) -> float | None:
    """The smallest distance of a changed point over both sides (None without distances)."""
    smallest = math.inf
    for stored in sides.values():
        for start in range(0, len(stored.labels), CHUNK_ROWS):
            changed = stored.labels[start : start + CHUNK_ROWS] == LABEL_CHANGED
            if changed.any():
                distances = stored.distances.read(start, start + CHUNK_ROWS)[changed]
                distances = distances[np.isfinite(distances)]
                if distances.size:
                    smallest = min(smallest, float(distances.min()))
    return smallest if math.isfinite(smallest) else None


def pool_rows(stored: StoredSide, change_threshold: float | None) -> NDArray[np.int64]:
    """Rows of the side's live-relabelling candidates (see
    :func:`~app.viewer.scene_parts.candidate_pool`): observed, at least half the threshold
    away, the farthest :data:`MAX_POOL_POINTS` kept (the selection pruned as it goes)."""
    if change_threshold is None:
        return np.zeros(0, np.int64)
    floor = POOL_FLOOR_FRACTION * change_threshold
    rows = np.zeros(0, np.int64)
    values = np.zeros(0, np.float32)
    for start in range(0, len(stored.labels), CHUNK_ROWS):
        distances = stored.distances.read(start, start + CHUNK_ROWS)
        observed = stored.labels[start : start + CHUNK_ROWS] != LABEL_UNOBSERVED
        with np.errstate(invalid="ignore"):
            found = np.flatnonzero(observed & (distances >= floor))
        rows = np.concatenate([rows, start + found])
        values = np.concatenate([values, distances[found]])
        if len(rows) > 2 * MAX_POOL_POINTS:
            rows, values = _farthest(rows, values)
    if len(rows) > MAX_POOL_POINTS:
        rows, values = _farthest(rows, values)
    return np.sort(rows)


def _farthest(
    rows: NDArray[np.int64], values: NDArray[np.float32]
) -> tuple[NDArray[np.int64], NDArray[np.float32]]:
    """The :data:`MAX_POOL_POINTS` rows of largest value (ties: the earlier rows)."""
    order = np.argsort(-values, kind="stable")[:MAX_POOL_POINTS]
    order.sort()
    return rows[order], values[order]


def read_rows(stored: StoredSide, rows: NDArray[np.int64]) -> NDArray[np.float64]:
    """The coordinates of sorted file ``rows``, shape (len(rows), 3), read a block at a time."""
    points = np.full((len(rows), 3), np.nan)
    with _blocks(stored) as opened:
        for start, block in opened.blocks:
            low, high = np.searchsorted(rows, [start, start + len(block)])
            points[low:high] = block[rows[low:high] - start]
    return points


def _blocks(stored: StoredSide) -> AbstractContextManager[PointBlocks]:
    """The side's file opened to be read a block at a time."""
    return open_point_blocks(
        stored.path, block_points=READ_BLOCK_POINTS, bag_options=stored.bag_options
    )


def budget_scene(
    sides: Mapping[str, StoredSide],
    context: SceneContext,
    point_budget: int = DEFAULT_POINT_BUDGET,
) -> SceneData:
    """The scene a browser opens with, read from the files (see the module's docstring)."""
    totals = label_totals(sides)
    counts = layer_counts(totals, point_budget)
    threshold = change_threshold_of(sides)
    gathered = {}
    for side, stored in sides.items():
        shown_rows = sorted_union(
            *(
                rows_with_label(stored.labels, label, strided_ranks(counts[(side, label)], total))
                for (name, label), total in totals.items()
                if name == side
            )
        )
        candidates = pool_rows(stored, threshold)
        rows = sorted_union(shown_rows, candidates)
        points = read_rows(stored, rows)
        if side == "scan":
            points = apply_transform(points, context.transform)
        gathered[side] = _gathered(stored, rows, points, shown_rows, candidates)
    sizes = {side: len(stored.labels) for side, stored in sides.items()}
    return assemble_scene(gathered, _layer_totals(totals), threshold, context, point_budget, sizes)


def box_scene(
    sides: Mapping[str, StoredSide],
    context: SceneContext,
    low: Sequence[float],
    high: Sequence[float],
    point_budget: int = DEFAULT_POINT_BUDGET,
    origin: NDArray[np.float64] | None = None,
) -> SceneData:
    """Every point inside the box ``low``-``high`` (reference frame, file coordinates) at full
    density, up to ``point_budget``; past it strided per layer, changed first, and a
    ``box_capped`` warning says how many points the box holds. ``origin``: the local origin of
    the view the box replaces (default: the box's own).

    Raises
    ------
    ValueError
        Corners that are not three finite numbers each, or low above high.
    """
    box_low, box_high = _checked_box(low, high)
    inside = {side: _box_filter(side, box_low, box_high, context) for side in sides}
    keep_limit = BOX_KEEP_BUDGETS * point_budget
    selected, totals = _select_in_box(sides, inside, lambda side, label: None, keep_limit)
    n_inside = sum(totals.values())
    capped = n_inside > point_budget
    if capped:  # a strided subset of each (side, label), changed first
        counts = layer_counts(totals, point_budget)
        ranks = {key: strided_ranks(counts[key], total) for key, total in totals.items()}
        if selected is None:  # too many to keep: a second pass keeps the subset only
            selected, _ = _select_in_box(sides, inside, lambda side, label: ranks[(side, label)])
        else:
            selected = {
                side: _strided_subset(sides[side].labels, rows, points, side, ranks)
                for side, (rows, points) in selected.items()
            }
    threshold = change_threshold_of(sides)
    floor = POOL_FLOOR_FRACTION * threshold if threshold is not None else math.inf
    gathered = {}
    for side, stored in sides.items():
        rows, points = selected[side]
        labels = stored.labels[rows]
        distances = stored.distances.at(rows, CHUNK_ROWS).astype(np.float32)
        with np.errstate(invalid="ignore"):
            pool = (labels != LABEL_UNOBSERVED) & (distances >= floor)
        gathered[side] = Gathered(rows, points, labels, distances, np.ones(len(rows), bool), pool)
    warnings = list(context.warnings)
    if capped:
        warnings.append(
            {
                "code": "box_capped",
                "message": f"the box holds {n_inside:,} points, more than the point budget of "
                f"{point_budget:,}: an evenly spread {point_budget:,} at most are shown "
                "(changed points first); clip to a smaller box for full density",
            }
        )
    scene_context = dataclasses.replace(context, warnings=warnings)
    sizes = {side: len(stored.labels) for side, stored in sides.items()}
    return assemble_scene(
        gathered, _layer_totals(totals), threshold, scene_context, point_budget, sizes, origin
    )


def _strided_subset(
    labels: NDArray[np.int8],
    rows: NDArray[np.int64],
    points: NDArray[np.float64],
    side: str,
    ranks: Mapping[tuple[str, int], NDArray[np.int64]],
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """The side's kept box points whose rank among those of their label is chosen."""
    keep = np.zeros(len(rows), dtype=bool)
    of_rows = labels[rows]
    for label in (LABEL_UNOBSERVED, LABEL_UNCHANGED, LABEL_CHANGED):
        keep[np.flatnonzero(of_rows == label)[ranks[(side, label)]]] = True
    return rows[keep], points[keep]


def _checked_box(
    low: Sequence[float], high: Sequence[float]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The box's corners as (3,) float64 arrays."""
    try:
        box_low = np.asarray(low, dtype=np.float64).reshape(3)
        box_high = np.asarray(high, dtype=np.float64).reshape(3)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"a box needs three numbers per corner: {exc}") from exc
    if not (np.isfinite(box_low).all() and np.isfinite(box_high).all()):
        raise ValueError("a box needs finite corners")
    if (box_low > box_high).any():
        raise ValueError(f"the box's low corner {box_low.tolist()} is above its high corner")
    return box_low, box_high


def _box_filter(
    side: str, low: NDArray[np.float64], high: NDArray[np.float64], context: SceneContext
) -> Callable[[NDArray[np.float64]], tuple[NDArray[np.float64], NDArray[np.bool_]]]:
    """For a block of the side's file: its points in the reference frame and which are inside."""

    def inside(block: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        points = apply_transform(block, context.transform) if side == "scan" else block
        with np.errstate(invalid="ignore"):
            return points, ((points >= low) & (points <= high)).all(axis=1)

    return inside


def _select_in_box(
    sides: Mapping[str, StoredSide],
    inside: Mapping[str, Callable],
    ranks_of: Callable[[str, int], NDArray[np.int64] | None],
    keep_limit: int | None = None,
) -> tuple[dict[str, tuple[NDArray[np.int64], NDArray[np.float64]]] | None, dict]:
    """Per side, the rows inside the box and their points (reference frame): all of them, or
    those whose rank among the box's points of their label is in ``ranks_of(side, label)``;
    and the box's points per (side, label). Past ``keep_limit`` points nothing more is kept
    (None is returned for the selection, the counts are complete)."""
    selected: dict[str, tuple[NDArray[np.int64], NDArray[np.float64]]] | None = {}
    counts: dict[tuple[str, int], int] = {}
    n_kept = 0
    for side, stored in sides.items():
        seen = dict.fromkeys((LABEL_UNOBSERVED, LABEL_UNCHANGED, LABEL_CHANGED), 0)
        rows_parts, points_parts = [], []
        with _blocks(stored) as opened:
            for start, block in opened.blocks:
                points, hit = inside[side](block)
                rows = start + np.flatnonzero(hit)
                labels = stored.labels[rows]
                keep = np.ones(len(rows), dtype=bool)
                for label in seen:
                    of_label = np.flatnonzero(labels == label)
                    ranks = ranks_of(side, label)
                    if ranks is not None and len(ranks) == 0:
                        keep[of_label] = False
                    elif ranks is not None:
                        rank = seen[label] + np.arange(len(of_label))
                        position = np.minimum(np.searchsorted(ranks, rank), len(ranks) - 1)
                        keep[of_label] = ranks[position] == rank
                    seen[label] += len(of_label)
                if selected is None:
                    continue
                n_kept += int(keep.sum())
                if keep_limit is not None and n_kept > keep_limit:
                    selected = None  # over the limit: only counting from here on
                    rows_parts, points_parts = [], []
                    continue
                rows_parts.append(rows[keep])
                points_parts.append(points[hit][keep])
        counts.update({(side, label): number for label, number in seen.items()})
        if selected is not None:
            selected[side] = (
                np.concatenate(rows_parts) if rows_parts else np.zeros(0, np.int64),
                np.concatenate(points_parts) if points_parts else np.zeros((0, 3)),
            )
    return selected, counts


def sorted_union(*arrays: NDArray[np.int64]) -> NDArray[np.int64]:
    """The distinct values of ``arrays``, sorted (one sort: faster than ``numpy.union1d``)."""
    values = np.sort(np.concatenate(arrays)) if arrays else np.zeros(0, np.int64)
    distinct = np.ones(len(values), dtype=bool)
    distinct[1:] = values[1:] != values[:-1]
    return values[distinct].astype(np.int64, copy=False)


def is_among(values: NDArray[np.int64], sorted_set: NDArray[np.int64]) -> NDArray[np.bool_]:
    """Whether each of ``values`` is in the sorted array ``sorted_set``, shape (len(values),)."""
    if len(sorted_set) == 0:
        return np.zeros(len(values), dtype=bool)
    position = np.minimum(np.searchsorted(sorted_set, values), len(sorted_set) - 1)
    return sorted_set[position] == values


def _layer_totals(totals: Mapping[tuple[str, int], int]) -> dict[str, int]:
    """Points per layer from points per (side, label)."""
    per_layer = {style.name: 0 for style in LAYER_STYLES}
    for key, total in totals.items():
        per_layer[LAYER_OF[key]] += total
    return per_layer


def _gathered(
    stored: StoredSide,
    rows: NDArray[np.int64],
    points: NDArray[np.float64],
    shown_rows: NDArray[np.int64],
    pool: NDArray[np.int64],
) -> Gathered:
    """The :class:`Gathered` of the side's read ``rows`` (sorted union of shown and pool)."""
    return Gathered(
        rows=rows,
        points=points,
        labels=stored.labels[rows],
        distances=stored.distances.at(rows, CHUNK_ROWS).astype(np.float32),
        shown=is_among(rows, shown_rows),
        pool=is_among(rows, pool),
    )


def assemble_scene(
    gathered: Mapping[str, Gathered],
    layer_totals: Mapping[str, int],
    change_threshold: float | None,
    context: SceneContext,
    point_budget: int,
    side_sizes: Mapping[str, int],
    origin: NDArray[np.float64] | None = None,
) -> SceneData:
    """The :class:`SceneData` of the points read per side (reference frame, file coordinates).

    ``origin``: the local origin (default: the drawn reference points' rounded centre).
    ``side_sizes`` are the rows of each side's file (the default minimum region size follows
    them). Non-finite rows (dropped by the readers, labelled unobserved) are left out. The
    candidate pools' spacing is measured among the points read (the pool at full density, the
    rest at the drawn density).
    """
    gathered = {side: _finite_only(part) for side, part in gathered.items()}
    reference, scan = gathered["reference"], gathered["scan"]
    if origin is None:
        drawn_reference = reference.points[reference.shown]
        origin = local_origin(drawn_reference if len(drawn_reference) else scan.points)
    layers = _layers(gathered, layer_totals, origin)
    sides = {
        side: SideCloud(
            side=side,
            points=np.ascontiguousarray(part.points[part.shown] - origin, dtype=np.float32),
            labels=part.labels[part.shown],
            distances=part.distances[part.shown],
            indices=part.rows[part.shown],
        )
        for side, part in gathered.items()
    }
    bounds_min, bounds_max, point_size = _bounds_and_point_size(layers)
    min_region_points = context.min_region_points
    if min_region_points is None:  # the localiser's default for clouds of these sizes
        smaller = min(side_sizes.values())
        min_region_points = max(
            MIN_REGION_POINTS_FLOOR, round(MIN_REGION_POINTS_PER_SQRT * math.sqrt(smaller))
        )
    sensor_origins = context.sensor_origins or {}
    return SceneData(
        origin=origin,
        layers=tuple(layers),
        regions=region_boxes(context.regions, origin),
        bounds_min=bounds_min,
        bounds_max=bounds_max,
        point_size=point_size,
        point_budget=int(point_budget),
        summary=dict(context.summary or {}),
        sides=sides,
        pools=_pools(gathered, change_threshold, origin),
        sensors=sensor_markers(sensor_origins, context.transform, origin),
        trajectories=trajectory_paths(sensor_origins, context.transform, origin),
        uncertain=region_boxes(context.uncertain_regions, origin),
        warnings=tuple(
            {"code": str(item.get("code", "")), "message": str(item.get("message", ""))}
            for item in context.warnings
            if isinstance(item, Mapping)
        ),
        change_threshold=change_threshold,
        min_region_points=max(int(min_region_points), 1),
    )


def _finite_only(part: Gathered) -> Gathered:
    """``part`` without its non-finite rows (the file's NaN rows, labelled unobserved)."""
    finite = np.isfinite(part.points).all(axis=1)
    if finite.all():
        return part
    return Gathered(
        part.rows[finite],
        part.points[finite],
        part.labels[finite],
        part.distances[finite],
        part.shown[finite],
        part.pool[finite],
    )


def _layers(
    gathered: Mapping[str, Gathered], layer_totals: Mapping[str, int], origin: NDArray[np.float64]
) -> list[Layer]:
    """The drawn layers (float32, local), with the layers' totals in the whole job or box."""
    layers = []
    for style in LAYER_STYLES:
        parts = [
            gathered[side].points[gathered[side].shown & (gathered[side].labels == label)]
            for (side, label), name in LAYER_OF.items()
            if name == style.name
        ]
        points = np.concatenate(parts) if parts else np.zeros((0, 3))
        layers.append(
            Layer(
                name=style.name,
                title=style.title,
                color=style.color,
                visible=style.visible,
                description=style.description,
                points=np.ascontiguousarray(points - origin, dtype=np.float32),
                n_total=int(layer_totals[style.name]),
            )
        )
    return layers


def _pools(
    gathered: Mapping[str, Gathered], change_threshold: float | None, origin: NDArray[np.float64]
) -> dict[str, CandidatePool]:
    """Per side, the candidates of live relabelling among the points read."""
    floor = POOL_FLOOR_FRACTION * change_threshold if change_threshold else 0.0
    return {
        side: CandidatePool(
            side=side,
            floor=float(floor),
            points=part.points[part.pool] - origin,
            distances=part.distances[part.pool],
            indices=part.rows[part.pool],
            changed=part.labels[part.pool] == LABEL_CHANGED,
            spacing=local_spacing(part.points, np.flatnonzero(part.pool)),
        )
        for side, part in gathered.items()
    }


def _bounds_and_point_size(layers: Sequence[Layer]) -> tuple[NDArray, NDArray, float]:
    """The 1st and 99th percentiles of the drawn points (what the camera frames), shape (3,)
    each, and a point size (as :func:`~app.viewer.scene.build_scene_data` gives them)."""
    drawn = [layer.points for layer in layers if layer.n_shown]
    if not drawn:
        return np.zeros(3), np.zeros(3), 0.05
    points = np.concatenate(drawn)
    bounds_min, bounds_max = np.percentile(points, [1.0, 99.0], axis=0)
    extent = float(np.linalg.norm(bounds_max - bounds_min))
    return bounds_min, bounds_max, estimate_point_size(points, extent)
