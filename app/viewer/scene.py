"""What the 3D view shows for one job, as plain arrays: the scene builder.

:func:`build_scene_data` turns a finished job (both clouds, the registration transform, the
per-point labels and the regions) into display layers and region boxes;
:mod:`app.viewer.viser_scene` draws them with viser.  Nothing here imports viser, so the
builder is unit-tested on synthetic data without a server.

Coordinates: the scan is drawn in the reference frame (the job's registration transform is applied),
and every displayed coordinate is relative to a rounded local origin and stored as float32, so
georeferenced scans (x ~ 5e5 m) keep their millimetres on the GPU.  Large clouds are randomly
subsampled (deterministically) to a point budget; changed points are kept first, and each layer
states how many of its points are shown.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.config import DEFAULT_VIEWER_POINT_BUDGET
from app.core.labels import LABEL_CHANGED, LABEL_UNCHANGED, LABEL_UNOBSERVED
from app.core.localise.changes import MIN_REGION_POINTS_FLOOR, MIN_REGION_POINTS_PER_SQRT
from app.core.registration import apply_transform
from app.viewer.ceiling import opening_clip_height
from app.viewer.colours import ADDED_COLOUR, REMOVED_COLOUR
from app.viewer.opening import OpeningView, choose_opening_view
from app.viewer.scene_parts import (
    SIDES,
    CandidatePool,
    SensorMarker,
    SideCloud,
    candidate_pool,
    check_distances,
    check_labels,
    sensor_markers,
    smallest_changed_distance,
    triple,
)
from app.viewer.trajectory_display import TrajectoryPath, trajectory_paths

DEFAULT_POINT_BUDGET = DEFAULT_VIEWER_POINT_BUDGET
"""Most points sent to a browser for one job (about 15 MB over the websocket); the default of
the ``viewer_point_budget`` setting."""

CHANGED_SHARE_OF_BUDGET = 0.5
"""Changed points (removed + added) may use at most this share of the budget."""

MIN_BOX_EDGE = 0.01
"""Region boxes are at least this wide (metres), so single-point regions stay visible."""

RGB = tuple[int, int, int]


@dataclass(frozen=True)
class LayerStyle:
    """How one layer is drawn."""

    name: str
    title: str
    color: RGB
    visible: bool
    description: str


QUIET_REFERENCE: RGB = (180, 140, 205)
"""Unchanged reference points: a pale violet, quieter than the changes' saturated red/green."""
QUIET_SCAN: RGB = (80, 160, 205)
"""Unchanged scan points: a pale blue, told apart from the reference, quieter than a change."""
CHANGED_LAYERS = ("removed", "added")
"""Drawn larger than the others and never darkened by the depth cue, so they stand out."""

LAYER_STYLES: tuple[LayerStyle, ...] = (
    LayerStyle("reference", "Reference", QUIET_REFERENCE, True, "unchanged reference points"),
    LayerStyle("scan", "Scan", QUIET_SCAN, True, "unchanged scan points"),
    LayerStyle("removed", "Removed", REMOVED_COLOUR, True, "in the reference, gone from the scan"),
    LayerStyle("added", "Added", ADDED_COLOUR, True, "in the scan, not in the reference"),
    LayerStyle(
        "unobserved", "Unobserved", (215, 215, 235), False, "seen by one scan only (not change)"
    ),
)
STYLE_BY_NAME: dict[str, LayerStyle] = {style.name: style for style in LAYER_STYLES}
MOVED_COLOR: RGB = (250, 170, 0)
"""A removed region and an added one close by, shown as one moved object."""
KIND_COLORS: dict[str, RGB] = {
    "removed": STYLE_BY_NAME["removed"].color,
    "added": STYLE_BY_NAME["added"].color,
    "moved": MOVED_COLOR,
}
SIDE_LAYERS: dict[str, tuple[str, str]] = {
    "reference": ("reference", "removed"),
    "scan": ("scan", "added"),
}
"""Per side: the layer of its unchanged points and the layer of its changed points."""


@dataclass(frozen=True, eq=False)
class Layer:
    """One coloured point layer: float32 points relative to the scene origin."""

    name: str
    title: str
    color: RGB
    visible: bool
    description: str
    points: NDArray[np.float32]
    n_total: int

    @property
    def n_shown(self) -> int:
        """Points actually drawn (after downsampling)."""
        return int(self.points.shape[0])

    def to_json_dict(self) -> dict[str, Any]:
        """Name, colour, default visibility and shown/total counts."""
        return {
            "name": self.name,
            "title": self.title,
            "color": list(self.color),
            "visible": self.visible,
            "shown": self.n_shown,
            "total": self.n_total,
        }


@dataclass(frozen=True)
class RegionBox:
    """A region's axis-aligned box, in file coordinates of the reference frame and locally."""

    index: int
    region_id: str | None
    kind: str
    n_points: int
    centroid: tuple[float, float, float]
    bbox_min: tuple[float, float, float]
    bbox_max: tuple[float, float, float]
    center_local: tuple[float, float, float]
    dimensions: tuple[float, float, float]
    mean_distance: float | None
    max_distance: float | None
    evidence: str = "seen_empty"
    confidence: float | None = None

    @property
    def color(self) -> RGB:
        """Red for removed, green for added."""
        return KIND_COLORS.get(self.kind, (240, 200, 0))

    @property
    def label(self) -> str:
        """Text of the region's button: number, kind, size and why it is a change."""
        why = EVIDENCE_WORDS.get(self.evidence, self.evidence)
        if self.confidence is not None:
            why = f"{why} {round(100 * self.confidence)} %"
        return f"#{self.index + 1} {self.kind} · {self.n_points:,} pts · {why}"

    @property
    def short_label(self) -> str:
        """Text drawn next to the box in the scene (short: many boxes may be close)."""
        return f"#{self.index + 1} {self.kind}"

    def to_json_dict(self) -> dict[str, Any]:
        """Plain JSON types."""
        return {
            "index": self.index,
            "region_id": self.region_id,
            "kind": self.kind,
            "n_points": self.n_points,
            "label": self.label,
            "centroid": list(self.centroid),
            "bbox_min": list(self.bbox_min),
            "bbox_max": list(self.bbox_max),
            "center_local": list(self.center_local),
            "dimensions": list(self.dimensions),
            "evidence": self.evidence,
            "confidence": self.confidence,
        }


EVIDENCE_WORDS = {
    "seen_empty": "seen empty",
    "surface_moved": "surface moved",
    "no_coverage": "not covered",
}
"""How a region's evidence reads on its button."""


@dataclass(frozen=True, eq=False)
class SceneData:
    """Everything the 3D view of one job draws."""

    origin: NDArray[np.float64]
    layers: tuple[Layer, ...]
    regions: tuple[RegionBox, ...]
    bounds_min: NDArray[np.float64]  # local frame: 1st/99th percentiles of the drawn points,
    bounds_max: NDArray[np.float64]  # what the camera frames (far stray returns ignored)
    point_size: float
    point_budget: int
    summary: Mapping[str, Any] = field(default_factory=dict)
    sides: Mapping[str, SideCloud] = field(default_factory=dict)
    pools: Mapping[str, CandidatePool] = field(default_factory=dict)
    sensors: tuple[SensorMarker, ...] = ()
    trajectories: tuple[TrajectoryPath, ...] = ()
    uncertain: tuple[RegionBox, ...] = ()
    """Places the other epoch never covered (evidence ``no_coverage``): drawn, never counted."""
    warnings: tuple[Mapping[str, str], ...] = ()
    change_threshold: float | None = None
    """The smallest distance of a changed point (metres): the job's threshold, from above."""
    min_region_points: int = 1
    """The job's minimum region size (points), as far as the viewer knows it."""

    @property
    def has_distances(self) -> bool:
        """Whether per-point distances were stored (jobs before details.npz have none)."""
        return any(np.isfinite(side.distances).any() for side in self.sides.values())

    def layer(self, name: str) -> Layer:
        """The layer called ``name``."""
        for layer in self.layers:
            if layer.name == name:
                return layer
        raise KeyError(name)

    @property
    def center(self) -> NDArray[np.float64]:
        """Centre of the bounds, local frame."""
        return (self.bounds_min + self.bounds_max) / 2.0

    @property
    def extent(self) -> float:
        """Length of the bounds' diagonal (metres), at least 1 mm."""
        return max(float(np.linalg.norm(self.bounds_max - self.bounds_min)), 1e-3)

    @cached_property
    def opening(self) -> OpeningView:
        """The camera and height clip a browser opens with: on the change, unhidden."""
        drawn = [side.points for side in self.sides.values()]
        points = np.concatenate(drawn) if drawn else np.zeros((0, 3), np.float32)
        changed = np.concatenate([self.layer(name).points for name in ("removed", "added")])
        change_tops = [r.center_local[2] + r.dimensions[2] / 2 for r in self.regions]
        if len(changed):
            change_tops.append(float(changed[:, 2].max()))
        clip_high = opening_clip_height(points, change_tops)
        unchanged = np.concatenate([self.layer(name).points for name in ("reference", "scan")])
        unchanged = unchanged[unchanged[:, 2] <= clip_high]
        boxes_low = [np.subtract(r.center_local, np.divide(r.dimensions, 2)) for r in self.regions]
        boxes_high = [np.add(r.center_local, np.divide(r.dimensions, 2)) for r in self.regions]
        return choose_opening_view(
            unchanged,
            changed,
            self.bounds_min,
            self.bounds_max,
            clip_high=clip_high,
            regions_low=np.array(boxes_low).reshape(-1, 3),
            regions_high=np.array(boxes_high).reshape(-1, 3),
        )

    @property
    def n_shown(self) -> int:
        """Points drawn over every layer."""
        return sum(layer.n_shown for layer in self.layers)

    @property
    def n_total(self) -> int:
        """Points in every layer before downsampling."""
        return sum(layer.n_total for layer in self.layers)

    def to_json_dict(self) -> dict[str, Any]:
        """The builder's record: origin, layers with counts, region boxes."""
        return {
            "origin": self.origin.tolist(),
            "point_size": self.point_size,
            "point_budget": self.point_budget,
            "shown": self.n_shown,
            "total": self.n_total,
            "layers": [layer.to_json_dict() for layer in self.layers],
            "regions": [region.to_json_dict() for region in self.regions],
            "uncertain_regions": [box.to_json_dict() for box in self.uncertain],
            "summary": dict(self.summary),
            "change_threshold": self.change_threshold,
            "min_region_points": self.min_region_points,
            "has_distances": self.has_distances,
            "sensors": [
                {
                    "side": marker.side,
                    "position": list(marker.position),
                    "source": marker.source,
                    "confidence": marker.confidence,
                }
                for marker in self.sensors
            ],
            "warnings": [dict(warning) for warning in self.warnings],
            "opening": self.opening.to_json_dict(self.origin),
        }


def local_origin(points: NDArray[np.float64], quantum: float = 1.0) -> NDArray[np.float64]:
    """Centre of the bounding box of ``points`` rounded to ``quantum`` metres.

    Unlike :func:`app.core.cloud.choose_local_origin` (zero near the origin, so the core's
    numbers match the file's), the display always centres: viser sends float32 and the camera
    orbits the origin.
    """
    if len(points) == 0:
        return np.zeros(3)
    centre = (points.min(axis=0) + points.max(axis=0)) / 2.0
    return np.round(centre / quantum) * quantum


def allocate_budget(totals: Mapping[str, int], budget: int) -> dict[str, int]:
    """Points to show per layer: changed layers first (up to half), the rest proportionally."""
    budget = max(int(budget), 0)
    if budget >= sum(totals.values()):
        return {name: int(total) for name, total in totals.items()}
    changed = [name for name in ("removed", "added") if name in totals]
    others = [name for name in totals if name not in changed]
    shown: dict[str, int] = {}
    changed_total = sum(totals[name] for name in changed)
    changed_budget = min(changed_total, int(budget * CHANGED_SHARE_OF_BUDGET))
    for name in changed:
        share = totals[name] / changed_total if changed_total else 0.0
        shown[name] = min(totals[name], int(changed_budget * share))
    remaining = budget - sum(shown.values())
    others_total = sum(totals[name] for name in others)
    for name in others:
        share = totals[name] / others_total if others_total else 0.0
        shown[name] = min(totals[name], int(remaining * share))
    return shown


def subsample(
    points: NDArray[np.float64], count: int, rng: np.random.Generator
) -> NDArray[np.float64]:
    """``count`` points of ``points`` chosen uniformly without replacement, in input order."""
    if count >= len(points):
        return points
    chosen = np.sort(rng.choice(len(points), size=count, replace=False))
    return points[chosen]


def estimate_point_size(
    points: NDArray[np.float32], extent: float = 0.0, sample_size: int = 2000
) -> float:
    """A point size (metres): 1.5x the median spacing, at least 1/800 of the scene's extent.

    The floor keeps sparse far-range lidar returns visible when the whole scene is in view.
    """
    if len(points) < 2:
        return 0.05
    rng = np.random.default_rng(0)
    sample = points if len(points) <= sample_size else points[rng.choice(len(points), sample_size)]
    from scipy.spatial import cKDTree  # on first use: API processes need no scipy

    tree = cKDTree(points if len(points) <= 200_000 else subsample(points, 200_000, rng))
    distances, _ = tree.query(sample, k=2)
    spacing = float(np.median(distances[:, 1]))
    if not np.isfinite(spacing) or spacing <= 0:
        extent = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
        spacing = max(extent, 1.0) / 500.0
    return max(1.5 * spacing, extent / 800.0)


def region_boxes(
    regions: Sequence[Mapping[str, Any]], origin: NDArray[np.float64]
) -> tuple[RegionBox, ...]:
    """Boxes of the API's regions (reference-frame file coordinates) relative to ``origin``."""
    boxes = []
    for index, region in enumerate(regions):
        low = np.asarray(region["bbox_min"], dtype=np.float64)
        high = np.asarray(region["bbox_max"], dtype=np.float64)
        dimensions = np.maximum(high - low, MIN_BOX_EDGE)
        center = (low + high) / 2.0 - origin
        boxes.append(
            RegionBox(
                index=index,
                region_id=region.get("id"),
                kind=str(region["kind"]),
                n_points=int(region["n_points"]),
                centroid=triple(region.get("centroid", (low + high) / 2.0)),
                bbox_min=triple(low),
                bbox_max=triple(high),
                center_local=triple(center),
                dimensions=triple(dimensions),
                mean_distance=_optional_float(region.get("mean_distance")),
                max_distance=_optional_float(region.get("max_distance")),
                evidence=str(region.get("evidence") or "seen_empty"),
                confidence=_optional_float(region.get("confidence")),
            )
        )
    return tuple(boxes)


def build_scene_data(
    reference_points: NDArray[np.float64],
    scan_points: NDArray[np.float64],
    *,
    reference_labels: NDArray | None = None,
    scan_labels: NDArray | None = None,
    reference_distances: NDArray | None = None,
    scan_distances: NDArray | None = None,
    transform: NDArray | Sequence[Sequence[float]] | None = None,
    regions: Sequence[Mapping[str, Any]] = (),
    uncertain_regions: Sequence[Mapping[str, Any]] = (),
    point_budget: int = DEFAULT_POINT_BUDGET,
    summary: Mapping[str, Any] | None = None,
    sensor_origins: Mapping[str, Any] | None = None,
    warnings: Sequence[Mapping[str, Any]] = (),
    min_region_points: int | None = None,
    random_state: int = 0,
) -> SceneData:
    """Layers and region boxes of one job.

    Parameters
    ----------
    reference_points, scan_points : ndarray, shape (n, 3)
        The clouds' finite points in their files' frames (``PointCloud.points``).
    reference_labels, scan_labels : ndarray of int8, per point of each cloud, optional
        0 unchanged, 1 changed, -1 unobserved (labels stored in file order are mapped with
        ``PointCloud.from_source_order``); None draws every point as unchanged.
    reference_distances, scan_distances : ndarray of float, per point of each cloud, optional
        Distance to the other cloud's surface (``details.npz``), NaN where unknown.
    transform : 4x4, optional
        Registration of the scan onto the reference (file frames); identity when None.
    regions : sequence of mappings
        The job's regions as the API returns them (``kind``, ``n_points``, ``bbox_min`` ...).
    uncertain_regions : sequence of mappings
        The job's ``uncertain_regions`` as :func:`app.viewer.loading.job_uncertain_regions`
        gives them (well-formed, evidence ``no_coverage``): drawn apart, never counted.
    point_budget : int
        Most points drawn over all layers.
    sensor_origins : mapping, optional
        ``{"reference": [{"origin": [x, y, z], "source": ..., "confidence": ...}], "scan": ...}``
        in each file's frame (the scan's are moved by ``transform``).
    warnings : sequence of mappings
        The job's quality warnings (``code``, ``message``).
    min_region_points : int, optional
        The job's minimum region size; else the localiser's default for these cloud sizes.
    """
    reference_points = np.asarray(reference_points, dtype=np.float64).reshape(-1, 3)
    scan_points = np.asarray(scan_points, dtype=np.float64).reshape(-1, 3)
    matrix = np.eye(4) if transform is None else np.asarray(transform, dtype=np.float64)
    if matrix.shape != (4, 4) or not np.isfinite(matrix).all():
        raise ValueError(f"the registration transform must be a finite 4x4 matrix, got {matrix!r}")
    scan_in_reference = apply_transform(scan_points, matrix)
    clouds = {"reference": reference_points, "scan": scan_in_reference}
    labels = {
        "reference": check_labels(reference_labels, len(reference_points), "reference"),
        "scan": check_labels(scan_labels, len(scan_points), "scan"),
    }
    distances = {
        "reference": check_distances(reference_distances, len(reference_points), "reference"),
        "scan": check_distances(scan_distances, len(scan_points), "scan"),
    }

    origin = local_origin(reference_points if len(reference_points) else scan_in_reference)
    layers, sides = _drawn_layers(clouds, labels, distances, origin, point_budget, random_state)
    bounds_min, bounds_max, point_size = _view_bounds(layers)
    change_threshold = smallest_changed_distance(labels, distances)
    if min_region_points is None:  # the localiser's default for clouds of these sizes
        min_region_points = max(
            MIN_REGION_POINTS_FLOOR,
            round(
                MIN_REGION_POINTS_PER_SQRT * math.sqrt(min(len(reference_points), len(scan_points)))
            ),
        )
    pools = {
        side: candidate_pool(
            side, clouds[side], labels[side], distances[side], origin, change_threshold
        )
        for side in SIDES
    }
    return SceneData(
        origin=origin,
        layers=tuple(layers),
        regions=region_boxes(regions, origin),
        bounds_min=bounds_min,
        bounds_max=bounds_max,
        point_size=point_size,
        point_budget=int(point_budget),
        summary=dict(summary or {}),
        sides=sides,
        pools=pools,
        sensors=sensor_markers(sensor_origins or {}, matrix, origin),
        trajectories=trajectory_paths(sensor_origins or {}, matrix, origin),
        uncertain=region_boxes(uncertain_regions, origin),
        warnings=tuple(
            {"code": str(item.get("code", "")), "message": str(item.get("message", ""))}
            for item in warnings
            if isinstance(item, Mapping)
        ),
        change_threshold=change_threshold,
        min_region_points=max(int(min_region_points), 1),
    )


def _drawn_layers(
    clouds: Mapping[str, NDArray[np.float64]],
    labels: Mapping[str, NDArray[np.int8]],
    distances: Mapping[str, NDArray],
    origin: NDArray[np.float64],
    point_budget: int,
    random_state: int,
) -> tuple[list[Layer], dict[str, SideCloud]]:
    """The layers drawn within ``point_budget`` points, and each side's drawn points."""
    selections: dict[str, list[tuple[str, NDArray[np.int64]]]] = {
        "reference": [("reference", np.flatnonzero(labels["reference"] == LABEL_UNCHANGED))],
        "scan": [("scan", np.flatnonzero(labels["scan"] == LABEL_UNCHANGED))],
        "removed": [("reference", np.flatnonzero(labels["reference"] == LABEL_CHANGED))],
        "added": [("scan", np.flatnonzero(labels["scan"] == LABEL_CHANGED))],
        "unobserved": [(side, np.flatnonzero(labels[side] == LABEL_UNOBSERVED)) for side in SIDES],
    }
    totals = {name: sum(len(rows) for _side, rows in parts) for name, parts in selections.items()}
    counts = allocate_budget(totals, point_budget)
    rng = np.random.default_rng(random_state)
    layers = []
    shown_rows: dict[str, list[NDArray[np.int64]]] = {side: [] for side in SIDES}
    for style in LAYER_STYLES:
        parts = selections[style.name]
        kept = _subsample_parts(parts, counts[style.name], totals[style.name], rng)
        for side, rows in kept:
            shown_rows[side].append(rows)
        points = [clouds[side][rows] for side, rows in kept]
        layers.append(
            Layer(
                name=style.name,
                title=style.title,
                color=style.color,
                visible=style.visible,
                description=style.description,
                points=np.ascontiguousarray(np.concatenate(points) - origin, dtype=np.float32),
                n_total=totals[style.name],
            )
        )
    sides = {}
    for side in SIDES:
        rows = np.sort(np.concatenate(shown_rows[side])).astype(np.int64)
        sides[side] = SideCloud(
            side=side,
            points=np.ascontiguousarray(clouds[side][rows] - origin, dtype=np.float32),
            labels=labels[side][rows],
            distances=distances[side][rows].astype(np.float32),
            indices=rows,
        )
    return layers, sides


def _view_bounds(layers: Sequence[Layer]) -> tuple[NDArray, NDArray, float]:
    """The 1st and 99th percentiles of the drawn points, shape (3,) each, and a point size."""
    drawn = [layer.points for layer in layers if layer.n_shown]
    if drawn:
        bounds_min, bounds_max = np.percentile(np.concatenate(drawn), [1.0, 99.0], axis=0)
    else:
        bounds_min = bounds_max = np.zeros(3)
    extent = float(np.linalg.norm(bounds_max - bounds_min))
    point_size = estimate_point_size(np.concatenate(drawn), extent) if drawn else 0.05
    return bounds_min, bounds_max, point_size


def _subsample_parts(
    parts: list[tuple[str, NDArray[np.int64]]], count: int, total: int, rng: np.random.Generator
) -> list[tuple[str, NDArray[np.int64]]]:
    """``count`` rows chosen uniformly over the concatenated ``parts``, per part, in order."""
    if count >= total:
        return parts
    chosen = np.sort(rng.choice(total, size=count, replace=False))
    kept = []
    start = 0
    for side, rows in parts:
        inside = chosen[(chosen >= start) & (chosen < start + len(rows))] - start
        kept.append((side, rows[inside]))
        start += len(rows)
    return kept


def _optional_float(value: Any) -> float | None:
    """``float(value)`` or None."""
    return None if value is None else float(value)
