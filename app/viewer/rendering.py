"""What one browser's 3D view draws under its current settings, as plain arrays.

:class:`ViewState` holds a reviewer's choices (colour mode, which scans, the height clip,
the depth cue, the change settings); :func:`render_layers` turns the scene's drawn points and
the current labels into the points and colours of each layer; :func:`pick_point` finds the
drawn point nearest a click's ray.  No viser here: :mod:`app.viewer.viser_scene` sends the
arrays.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.core.labels import LABEL_CHANGED, LABEL_UNCHANGED, LABEL_UNOBSERVED
from app.viewer.colours import (
    distance_limit,
    shade_by_height,
    signed_distance_colours,
)
from app.viewer.scene import (
    CHANGED_LAYERS,
    SIDE_LAYERS,
    SIDES,
    STYLE_BY_NAME,
    SceneData,
)

COLOUR_MODES = {"label": "By label", "distance": "By signed distance"}
SHOW_CHOICES = {
    "both": "Both",
    "reference": "Reference (before)",
    "scan": "Scan (after)",
}
PICK_PIXELS = 8.0
"""A click picks a point drawn within this many pixels of the cursor."""


@dataclass
class ViewState:
    """One browser's choices."""

    colour_mode: str = "label"
    show: str = "both"
    clip_low: float = -np.inf
    clip_high: float = np.inf
    depth_cue: bool = True
    layer_visible: dict[str, bool] = field(default_factory=dict)
    min_distance: float | None = None
    """None: the job's own labels; else relabelled live at this threshold (metres)."""
    min_region_points: int | None = None
    moved_within: float = 1.0
    constant_screen_size: bool = True
    point_pixels: float = 3.0

    @property
    def relabelled(self) -> bool:
        """Whether the labels differ from the job's (a change slider was moved)."""
        return self.min_distance is not None or self.min_region_points is not None

    def to_json_dict(self) -> dict[str, Any]:
        """Plain JSON values (infinite clip bounds as None)."""
        return {
            "colour_mode": self.colour_mode,
            "show": self.show,
            "clip": [
                None if not np.isfinite(self.clip_low) else self.clip_low,
                None if not np.isfinite(self.clip_high) else self.clip_high,
            ],
            "depth_cue": self.depth_cue,
            "min_distance": self.min_distance,
            "min_region_points": self.min_region_points,
            "moved_within": self.moved_within,
            "constant_screen_size": self.constant_screen_size,
            "point_pixels": self.point_pixels,
        }


@dataclass(frozen=True, eq=False)
class RenderedLayer:
    """A layer's points (local, float32) and colours (uint8), and where each point came from."""

    name: str
    points: NDArray[np.float32]
    colours: NDArray[np.uint8]
    sides: NDArray[np.int8]
    """0 reference, 1 scan."""
    rows: NDArray[np.int64]
    """Index into that side's :class:`~app.viewer.scene.SideCloud`."""

    @property
    def n_points(self) -> int:
        """Points in the layer."""
        return int(self.points.shape[0])


def colour_limit(data: SceneData) -> float:
    """The signed-distance colour map's limit for this scene (metres)."""
    return distance_limit([side.distances for side in data.sides.values()], data.change_threshold)


def render_layers(
    data: SceneData, state: ViewState, labels: Mapping[str, NDArray[np.int8]]
) -> dict[str, RenderedLayer]:
    """Points and colours of every layer under ``state``, with ``labels`` per side."""
    limit = colour_limit(data)
    low, high = float(data.bounds_min[2]), float(data.bounds_max[2])
    parts: dict[str, list[tuple[int, NDArray[np.int64]]]] = {name: [] for name in STYLE_BY_NAME}
    for number, side_name in enumerate(SIDES):
        if state.show not in ("both", side_name):
            continue
        side = data.sides[side_name]
        side_labels = labels[side_name]
        heights = side.points[:, 2]
        inside = (heights >= state.clip_low) & (heights <= state.clip_high)
        unchanged_layer, changed_layer = SIDE_LAYERS[side_name]
        for layer, label in (
            (unchanged_layer, LABEL_UNCHANGED),
            (changed_layer, LABEL_CHANGED),
            ("unobserved", LABEL_UNOBSERVED),
        ):
            parts[layer].append((number, np.flatnonzero(inside & (side_labels == label))))
    rendered = {}
    for name, style in STYLE_BY_NAME.items():
        sides = [np.full(len(rows), number, dtype=np.int8) for number, rows in parts[name]]
        rows = [rows for _number, rows in parts[name]]
        side_numbers = np.concatenate(sides) if sides else np.zeros(0, np.int8)
        row_numbers = np.concatenate(rows) if rows else np.zeros(0, np.int64)
        points = _gather(data, side_numbers, row_numbers, "points").reshape(-1, 3)
        if state.colour_mode == "distance" and name != "unobserved":
            signed = _gather(data, side_numbers, row_numbers, "signed_distances")
            colours = signed_distance_colours(signed, limit)
        else:
            colours = np.broadcast_to(np.array(style.color, np.uint8), (len(points), 3))
        if state.depth_cue and len(points) and name not in CHANGED_LAYERS:  # changes stay bright
            colours = shade_by_height(colours, points[:, 2], low, high)
        rendered[name] = RenderedLayer(
            name=name,
            points=np.ascontiguousarray(points, dtype=np.float32),
            colours=np.ascontiguousarray(colours, dtype=np.uint8),
            sides=side_numbers,
            rows=row_numbers,
        )
    return rendered


def _gather(
    data: SceneData, side_numbers: NDArray[np.int8], rows: NDArray[np.int64], attribute: str
) -> NDArray:
    """``attribute`` of the drawn points named by (side number, row) pairs, in that order."""
    pieces = []
    for number, side_name in enumerate(SIDES):
        values = np.asarray(getattr(data.sides[side_name], attribute))
        pieces.append(values[rows[side_numbers == number]])
    order = np.argsort(side_numbers, kind="stable")
    out = np.empty((len(rows), *pieces[0].shape[1:]), dtype=pieces[0].dtype)
    out[order] = np.concatenate(pieces)
    return out


@dataclass(frozen=True)
class Picked:
    """A drawn point a reviewer clicked."""

    layer: str
    side: str
    row: int
    """Row of the side's full cloud."""
    position: tuple[float, float, float]
    """File coordinates of the reference frame."""
    label: int
    distance: float | None
    """Signed distance (metres): negative on the reference, positive on the scan."""

    @property
    def label_name(self) -> str:
        """changed/unchanged/unobserved, with the side's kind of change."""
        if self.label == LABEL_CHANGED:
            return "removed" if self.side == "reference" else "added"
        return "unobserved" if self.label == LABEL_UNOBSERVED else "unchanged"

    def to_json_dict(self) -> dict[str, Any]:
        """Plain JSON values."""
        return {
            "layer": self.layer,
            "side": self.side,
            "row": self.row,
            "position": list(self.position),
            "label": self.label_name,
            "distance": self.distance,
        }

    def markdown(self) -> str:
        """What the GUI shows of it."""
        x, y, z = self.position
        distance = "unknown" if self.distance is None else f"{self.distance:+.3f} m"
        return (
            f"**{self.side.capitalize()} point {self.row:,}**  \n"
            f"x {x:.3f}, y {y:.3f}, z {z:.3f}  \n"
            f"label: **{self.label_name}**  \nsigned distance: {distance}"
        )


def pick_point(
    data: SceneData,
    layers: Mapping[str, RenderedLayer],
    visible: Mapping[str, bool],
    labels: Mapping[str, NDArray[np.int8]],
    ray_origin: NDArray[np.floating],
    ray_direction: NDArray[np.floating],
    pixel_angle: float,
    point_radius: float = 0.0,
) -> Picked | None:
    """The visible drawn point nearest the camera among those within :data:`PICK_PIXELS` of
    the ray (``pixel_angle``: radians per screen pixel) plus their drawn radius, or None."""
    origin = np.asarray(ray_origin, dtype=np.float64)
    direction = np.asarray(ray_direction, dtype=np.float64)
    direction = direction / max(float(np.linalg.norm(direction)), 1e-12)
    best: tuple[float, str, int] | None = None
    for name, layer in layers.items():
        if not visible.get(name, False) or layer.n_points == 0:
            continue
        offsets = layer.points.astype(np.float64) - origin
        along = offsets @ direction
        across_squared = np.einsum("ij,ij->i", offsets, offsets) - along * along
        tolerance = np.maximum(along, 0.0) * np.tan(pixel_angle * PICK_PIXELS) + point_radius
        hits = np.flatnonzero((along > 0) & (across_squared <= tolerance * tolerance))
        if len(hits) == 0:
            continue
        nearest = hits[np.argmin(along[hits])]
        if best is None or along[nearest] < best[0]:
            best = (float(along[nearest]), name, int(nearest))
    if best is None:
        return None
    _, name, index = best
    layer = layers[name]
    side_name = SIDES[int(layer.sides[index])]
    side = data.sides[side_name]
    row = int(layer.rows[index])
    signed = float(side.signed_distances[row])
    position = side.points[row].astype(np.float64) + data.origin
    return Picked(
        layer=name,
        side=side_name,
        row=int(side.indices[row]),
        position=(float(position[0]), float(position[1]), float(position[2])),
        label=int(labels[side_name][row]),
        distance=signed if np.isfinite(signed) else None,
    )
