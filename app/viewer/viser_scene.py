"""Draw a :class:`~app.viewer.scene.SceneData` in a viser server, one private copy per browser.

Each browser that connects gets its own scene nodes and GUI (``client.scene``/``client.gui``),
so one reviewer hiding a layer or moving the camera does not change what another reviewer
sees.  :class:`ClientScene` keeps the handles, which is what tests and the scene endpoint read
back as "what viser is showing".
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import viser

from app.viewer.scene import Layer, RegionBox, SceneData

MAX_REGION_BUTTONS = 40
"""Region list length in the GUI; the largest regions are listed first beyond this."""

MAX_REGION_LABELS = 20
"""Regions whose box gets a text label in the scene (the largest); more would hide the data."""

UP_DIRECTION = "+z"


@dataclass
class ClientScene:
    """The nodes and controls drawn for one connected browser."""

    client_id: int
    client: viser.ClientHandle | None = None
    point_clouds: dict[str, viser.PointCloudHandle] = field(default_factory=dict)
    boxes: list[tuple[RegionBox, viser.BoxHandle]] = field(default_factory=list)
    labels: list[viser.LabelHandle] = field(default_factory=list)

    def to_json_dict(self, origin: np.ndarray) -> dict[str, Any]:
        """What viser holds for this client: layers (visibility, sizes) and boxes (file frame)."""
        camera = None
        if self.client is not None:
            camera = {
                "look_at": (np.asarray(self.client.camera.look_at) + origin).tolist(),
                "position": (np.asarray(self.client.camera.position) + origin).tolist(),
            }
        return {
            "client_id": self.client_id,
            "camera": camera,
            "layers": {
                name: {
                    "visible": bool(handle.visible),
                    "n_points": int(np.asarray(handle.points).shape[0]),
                    "point_size": float(handle.point_size),
                }
                for name, handle in self.point_clouds.items()
            },
            "boxes": [
                {
                    "name": handle.name,
                    "kind": region.kind,
                    "visible": bool(handle.visible),
                    "center": (np.asarray(handle.position) + origin).tolist(),
                    "dimensions": np.asarray(handle.dimensions, dtype=float).tolist(),
                    "bbox_min": (
                        np.asarray(handle.position)
                        + origin
                        - np.asarray(handle.dimensions, dtype=float) / 2.0
                    ).tolist(),
                    "bbox_max": (
                        np.asarray(handle.position)
                        + origin
                        + np.asarray(handle.dimensions, dtype=float) / 2.0
                    ).tolist(),
                }
                for region, handle in self.boxes
            ],
        }


def configure_server(server: viser.ViserServer, data: SceneData, title: str) -> None:
    """Server-wide settings: theme without the share button, up axis, initial camera."""
    server.gui.configure_theme(
        show_share_button=False,  # it calls a tunnel service on the internet
        show_logo=False,
        control_width="medium",
        titlebar_content=None,
    )
    server.scene.set_up_direction(UP_DIRECTION)
    # Points and boxes are flat-coloured: shadow maps only cost time (a lot in software WebGL).
    server.scene.configure_default_lights(enabled=True, cast_shadow=False)
    server.scene.configure_environment_map(hdri=None)  # its PMREM passes are slow in software
    center = data.center
    server.initial_camera.look_at = tuple(center)
    server.initial_camera.position = tuple(center + default_camera_offset(data.extent))
    server.initial_camera.near = max(data.extent * 1e-4, 1e-3)
    server.initial_camera.far = max(data.extent * 20.0, 100.0)
    del title


def default_camera_offset(extent: float) -> np.ndarray:
    """Camera position relative to what it looks at: from the south-west, above."""
    direction = np.array([-0.55, -0.75, 0.55])
    return direction / np.linalg.norm(direction) * max(extent, 0.5) * 1.0


def build_client_scene(client: viser.ClientHandle, data: SceneData, title: str) -> ClientScene:
    """Add layers, region boxes and the GUI for one browser."""
    record = ClientScene(client_id=client.client_id, client=client)
    scene, gui = client.scene, client.gui
    for layer in data.layers:
        record.point_clouds[layer.name] = scene.add_point_cloud(
            f"/layers/{layer.name}",
            points=_nonempty(layer.points),
            colors=layer.color,
            point_size=data.point_size * (0.6 if layer.name == "unobserved" else 1.0),
            point_shape="rounded",
            point_shading="flat",
            precision="float32",
            visible=layer.visible and layer.n_shown > 0,
        )
    labelled = {
        region.index
        for region in sorted(data.regions, key=lambda region: -region.n_points)[:MAX_REGION_LABELS]
    }
    for region in data.regions:
        box = scene.add_box(
            f"/regions/{region.index}",
            color=region.color,
            dimensions=region.dimensions,
            wireframe=True,
            position=region.center_local,
            cast_shadow=False,
            receive_shadow=False,
        )
        record.boxes.append((region, box))
        if region.index not in labelled:
            continue
        corner = np.asarray(region.center_local) + np.asarray(region.dimensions) / 2.0
        label = scene.add_label(
            f"/region_labels/{region.index}",
            region.short_label,
            position=tuple(corner),
            anchor="bottom-left",
        )
        record.labels.append(label)

    with client.atomic():
        _add_summary(gui, data, title)
        _add_layer_controls(gui, data, record)
        _add_region_list(gui, client, data, record)
    return record


def _add_summary(gui: viser.GuiApi, data: SceneData, title: str) -> None:
    """The job's decision and the shown/total point counts."""
    lines = [f"**{title}**"]
    summary = data.summary
    if summary.get("score") is not None:
        decision = "changed" if summary.get("changed") else "no change"
        threshold = summary.get("threshold")
        limit = f" (threshold {threshold:.4g})" if threshold is not None else ""
        lines.append(f"Score {summary['score']:.4g}{limit}: **{decision}**")
    lines.append(
        f"Showing {data.n_shown:,} of {data.n_total:,} points"
        + (" (downsampled for display)" if data.n_shown < data.n_total else "")
    )
    gui.add_markdown("  \n".join(lines))


def _add_layer_controls(gui: viser.GuiApi, data: SceneData, record: ClientScene) -> None:
    """A checkbox per layer, one for the region boxes, and the point size slider."""
    with gui.add_folder("Layers"):
        for layer in data.layers:
            checkbox = gui.add_checkbox(
                _layer_label(layer),
                initial_value=layer.visible and layer.n_shown > 0,
                disabled=layer.n_shown == 0,
                hint=f"{layer.description}: {layer.n_shown:,} shown of {layer.n_total:,}",
            )
            checkbox.on_update(_visibility_toggle(record.point_clouds[layer.name]))
        boxes_checkbox = gui.add_checkbox(
            f"Region boxes ({len(data.regions)})", initial_value=True, disabled=not data.regions
        )

        @boxes_checkbox.on_update
        def _(event: viser.GuiEvent) -> None:
            for _region, handle in record.boxes:
                handle.visible = event.target.value
            for label in record.labels:
                label.visible = event.target.value

        size = data.point_size
        slider = gui.add_slider(
            "Point size",
            min=_round_size(size / 10.0),
            max=_round_size(size * 10.0),
            step=_round_size(size / 10.0),
            initial_value=_round_size(size),
            hint="point diameter in metres",
        )

        @slider.on_update
        def _(event: viser.GuiEvent) -> None:
            for name, handle in record.point_clouds.items():
                factor = 0.6 if name == "unobserved" else 1.0
                handle.point_size = float(event.target.value) * factor


def _add_region_list(
    gui: viser.GuiApi, client: viser.ClientHandle, data: SceneData, record: ClientScene
) -> None:
    """One button per region that moves this browser's camera to it."""
    regions = sorted(data.regions, key=lambda region: -region.n_points)[:MAX_REGION_BUTTONS]
    title = f"Regions ({len(data.regions)})"
    with gui.add_folder(title, expand_by_default=bool(regions)):
        if not data.regions:
            gui.add_markdown("No changed regions.")
            return
        if len(data.regions) > len(regions):
            gui.add_markdown(f"The {len(regions)} largest of {len(data.regions)} are listed.")
        if len(data.regions) > MAX_REGION_LABELS:
            gui.add_markdown(f"Labels are drawn on the {MAX_REGION_LABELS} largest.")
        for region in regions:
            button = gui.add_button(
                region.label,
                color="red" if region.kind == "removed" else "green",
                hint=f"centroid {', '.join(f'{value:.2f}' for value in region.centroid)}",
            )
            button.on_click(_camera_mover(client, region))
        reset = gui.add_button("Whole scene")

        @reset.on_click
        def _(_event: viser.GuiEvent) -> None:
            with client.atomic():  # position first: viser's position setter moves look_at too
                client.camera.position = tuple(data.center + default_camera_offset(data.extent))
                client.camera.look_at = tuple(data.center)


def _camera_mover(client: viser.ClientHandle, region: RegionBox) -> Any:
    """A click handler that frames ``region`` from the camera's current direction."""
    lock = threading.Lock()

    def move(_event: viser.GuiEvent) -> None:
        with lock:
            center = np.asarray(region.center_local, dtype=np.float64)
            direction = np.asarray(client.camera.position) - np.asarray(client.camera.look_at)
            norm = float(np.linalg.norm(direction))
            direction = direction / norm if norm > 1e-9 else default_camera_offset(1.0)
            distance = max(float(np.linalg.norm(region.dimensions)) * 2.0, 1.0)
            with client.atomic():  # position first: viser's position setter moves look_at too
                client.camera.position = tuple(center + direction * distance)
                client.camera.look_at = tuple(center)

    return move


def _visibility_toggle(handle: viser.PointCloudHandle) -> Any:
    """A checkbox handler that shows or hides ``handle``."""

    def toggle(event: viser.GuiEvent) -> None:
        handle.visible = bool(event.target.value)

    return toggle


def _layer_label(layer: Layer) -> str:
    """Checkbox text: title and shown/total counts."""
    if layer.n_shown == layer.n_total:
        return f"{layer.title} ({layer.n_total:,})"
    return f"{layer.title} ({layer.n_shown:,}/{layer.n_total:,})"


def _round_size(value: float) -> float:
    """``value`` to two significant digits, at least 1e-4."""
    value = max(float(value), 1e-4)
    return float(f"{value:.2g}")


def _nonempty(points: np.ndarray) -> np.ndarray:
    """viser needs at least one point; an empty layer gets one hidden point at the origin."""
    return points if len(points) else np.zeros((1, 3), dtype=np.float32)
