"""Draw a :class:`~app.viewer.scene.SceneData` in a viser server, one private copy per browser.

Each browser that connects gets its own scene nodes and GUI (``client.scene``/``client.gui``),
so one reviewer hiding a layer or moving the camera does not change what another reviewer
sees.  :class:`ClientScene` keeps the handles and the reviewer's settings
(:class:`~app.viewer.rendering.ViewState`), redraws when a control changes, and is what tests
and the scene endpoint read back as "what viser is showing".  The controls themselves are in
:mod:`app.viewer.controls`.

viser 1.1 sizes points in world units and has no eye-dome lighting, so the view keeps points a
constant size on the screen by resizing them from the camera's distance whenever the camera
moves, and shades points by height as a depth cue (:mod:`app.viewer.colours`).
"""

from __future__ import annotations

import hashlib
import logging
import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import viser

from app.viewer import controls
from app.viewer.box_controls import BoxLoader
from app.viewer.regions_display import (
    CameraView,
    MovedPair,
    Relabelled,
    box_edges,
    declutter,
    pair_moved,
    screen_box,
)
from app.viewer.rendering import Picked, RenderedLayer, ViewState, pick_point, render_layers
from app.viewer.scene import (
    CHANGED_LAYERS,
    MOVED_COLOR,
    SIDES,
    STYLE_BY_NAME,
    RegionBox,
    SceneData,
    SensorMarker,
)
from app.viewer.trajectory_display import draw_trajectory_paths
from app.viewer.uncertain_display import draw_uncertain_regions

logger = logging.getLogger("scandiff.viewer")

MAX_REGION_LABELS = 20
"""Regions whose box gets a text label in the scene (the largest); more would hide the data."""

UP_DIRECTION = "+z"
UNOBSERVED_SIZE_FACTOR = 0.6
CHANGED_SIZE_FACTOR = 1.6
"""Changed points are drawn this much larger than unchanged ones: the change stands out."""
BOX_LINE_PIXELS = 2.0


@dataclass
class ClientScene:
    """The nodes, controls and settings of one connected browser."""

    client_id: int
    client: viser.ClientHandle | None = None
    data: SceneData | None = None
    state: ViewState = field(default_factory=ViewState)
    point_clouds: dict[str, viser.PointCloudHandle] = field(default_factory=dict)
    rendered: dict[str, RenderedLayer] = field(default_factory=dict)
    boxes: list[tuple[RegionBox, Any]] = field(default_factory=list)
    labels: list[tuple[str, Any]] = field(default_factory=list)
    label_owners: list[tuple[int, ...]] = field(default_factory=list)
    """Per region label, the regions it names (a moved pair's label names two)."""
    moved: tuple[MovedPair, ...] = ()
    moved_nodes: list[Any] = field(default_factory=list)
    sensor_nodes: list[Any] = field(default_factory=list)
    uncertain_nodes: list[tuple[RegionBox, Any]] = field(default_factory=list)
    """The uncertain regions' dashed outlines (not changes: never counted nor relabelled)."""
    uncertain_visible: bool = True
    picked: Picked | None = None
    picked_node: Any = None
    relabelled: Relabelled | None = None
    boxes_visible: bool = True
    world_point_size: float = 0.05
    controls: dict[str, Any] = field(default_factory=dict)
    box_loader: BoxLoader | None = None
    """Reads a box of the job at full density (the "Full density in a box" panel)."""
    lock: threading.RLock = field(default_factory=threading.RLock)
    _layer_digest: dict[str, str] = field(default_factory=dict)
    _redraw_lock: threading.Lock = field(default_factory=threading.Lock)
    _pending_points: bool = False
    _pending_regions: bool = False
    _redrawing: bool = False

    # -- what is drawn ------------------------------------------------------------------------

    @property
    def regions(self) -> tuple[RegionBox, ...]:
        """The regions drawn: the job's, or those of the live relabelling."""
        assert self.data is not None
        return self.relabelled.regions if self.relabelled is not None else self.data.regions

    def current_labels(self) -> dict[str, np.ndarray]:
        """Labels of each side's drawn points under the current change settings."""
        assert self.data is not None
        if self.relabelled is None:
            return {side: self.data.sides[side].labels for side in SIDES}
        return {side: self.relabelled.labels_of(self.data.sides[side]) for side in SIDES}

    def layer_visible(self, name: str) -> bool:
        """Whether layer ``name`` is shown (its checkbox, and it has points)."""
        return self.state.layer_visible.get(name, STYLE_BY_NAME[name].visible) and bool(
            self.rendered.get(name) is not None and self.rendered[name].n_points
        )

    def request_redraw(self, points: bool = False, regions: bool = False) -> None:
        """Redraw soon, on one thread per browser: requests made while a redraw runs are merged
        into the next one, so dragging a slider over a large scene does not queue up redraws."""
        with self._redraw_lock:
            self._pending_points |= points
            self._pending_regions |= regions
            if self._redrawing:
                return
            self._redrawing = True
        threading.Thread(
            target=self._drain_redraws, name="scandiff-view-redraw", daemon=True
        ).start()

    def _drain_redraws(self) -> None:
        """Run the pending redraws until none is left."""
        while True:
            with self._redraw_lock:
                points, regions = self._pending_points, self._pending_regions
                self._pending_points = self._pending_regions = False
                if not (points or regions):
                    self._redrawing = False
                    return
            try:
                if points:
                    self.redraw_points()
                if regions:
                    self.redraw_regions()
            except Exception:  # a browser that left mid-redraw, or a bug: log, keep serving
                logger.exception("3D view redraw failed")

    def redraw_points(self) -> None:
        """Send every layer whose points or colours changed."""
        assert self.client is not None and self.data is not None
        with self.lock:
            self.rendered = render_layers(self.data, self.state, self.current_labels())
            with self.client.atomic():
                for name, layer in self.rendered.items():
                    digest = _digest(layer)
                    handle = self.point_clouds.get(name)
                    if handle is not None and self._layer_digest.get(name) == digest:
                        handle.visible = self.layer_visible(name)
                        continue
                    self._layer_digest[name] = digest
                    points, colours = layer.points, layer.colours
                    if not layer.n_points:  # viser needs a point: a hidden one at the origin
                        points, colours = np.zeros((1, 3), np.float32), np.zeros((1, 3), np.uint8)
                    self.point_clouds[name] = self.client.scene.add_point_cloud(
                        f"/layers/{name}",
                        points=points,
                        colors=colours,
                        point_size=self._point_size(name),
                        point_shape="rounded",
                        point_shading="gradient",  # sphere-like shading: a little depth
                        precision="float32",
                        visible=self.layer_visible(name),
                    )

    def redraw_regions(self) -> None:
        """Region outlines, moved pairs and labels for the current settings."""
        assert self.client is not None and self.data is not None
        scene = self.client.scene
        with self.lock, self.client.atomic():
            for node in [handle for _r, handle in self.boxes] + [h for _t, h in self.labels]:
                node.remove()
            for node in self.moved_nodes + [handle for _box, handle in self.uncertain_nodes]:
                node.remove()
            self.boxes, self.labels, self.moved_nodes = [], [], []
            self.uncertain_nodes = draw_uncertain_regions(
                scene,
                self.data.uncertain,
                visible=self.uncertain_visible,
                inside_clip=self._inside_clip,
            )
            self.label_owners = []
            regions = self.regions
            self.moved = pair_moved(regions, self.state.moved_within)
            paired = {pair.removed.index for pair in self.moved} | {
                pair.added.index for pair in self.moved
            }
            for region in regions:
                colour = MOVED_COLOR if region.index in paired else region.color
                handle = scene.add_line_segments(
                    f"/regions/{region.index}",
                    points=box_edges(region.center_local, region.dimensions),
                    colors=colour,
                    thickness=BOX_LINE_PIXELS,
                    thickness_units="screen",
                    visible=self.boxes_visible and self._inside_clip(region),
                )
                self.boxes.append((region, handle))
            # text, anchor, priority (points), the regions it names
            texts: list[tuple[str, np.ndarray, int, tuple[int, ...]]] = []
            for pair in self.moved:
                start = np.asarray(pair.removed.center_local)
                end = np.asarray(pair.added.center_local)
                self.moved_nodes.append(
                    scene.add_line_segments(
                        f"/moved/{pair.removed.index}-{pair.added.index}",
                        points=np.array([[start, end]], dtype=np.float32),
                        colors=MOVED_COLOR,
                        thickness=BOX_LINE_PIXELS,
                        thickness_units="screen",
                        visible=self.boxes_visible,
                    )
                )
                priority = pair.removed.n_points + pair.added.n_points
                owners = (pair.removed.index, pair.added.index)
                texts.append((pair.label, (start + end) / 2.0, priority, owners))
            for region in regions:
                if region.index not in paired:
                    corner = np.asarray(region.center_local) + np.asarray(region.dimensions) / 2
                    texts.append((region.short_label, corner, region.n_points, (region.index,)))
            texts.sort(key=lambda item: -item[2])
            for number, (text, anchor, _priority, owners) in enumerate(texts[:MAX_REGION_LABELS]):
                label = scene.add_label(
                    f"/region_labels/{number}", text, position=tuple(anchor), anchor="bottom-left"
                )
                self.labels.append((text, label))
                self.label_owners.append(owners)
        self.declutter()
        controls.refresh_change_status(self)

    @property
    def sensor_labels(self) -> list[Any]:
        """The sensors' label nodes."""
        return [node for node in self.sensor_nodes if isinstance(node, viser.LabelHandle)]

    def declutter(self) -> None:
        """Place every label (sensors first, then the largest regions) where it overlaps no
        other label and, if it can, no other region's box, from this camera; hide the rest."""
        assert self.data is not None
        with self.lock:
            sensors = self.sensor_labels
            handles = sensors + [handle for _text, handle in self.labels]
            if not handles:
                return
            owners = [()] * len(sensors) + list(self.label_owners)
            camera = self.camera_view()
            screen: dict[int, tuple[float, float, float, float]] = {}
            if camera is not None:
                for region, box in self.boxes:
                    if box.visible:
                        found = screen_box(camera, region.center_local, region.dimensions)
                        if found is not None:
                            screen[region.index] = found
            shown = declutter(
                np.array([np.asarray(handle.position) for handle in handles]),
                [handle.text for handle in handles],
                camera,
                world_separation=self.data.extent / 30.0,
                obstacles=[
                    [box for index, box in screen.items() if index not in named] for named in owners
                ],
                placed_together=len(sensors),
            )
            for number, (handle, anchor) in enumerate(zip(handles, shown, strict=True)):
                visible = anchor is not None and (number < len(sensors) or self.boxes_visible)
                if anchor is not None and handle.anchor != anchor:
                    handle.anchor = anchor
                if handle.visible != visible:
                    handle.visible = visible

    def camera_view(self) -> CameraView | None:
        """The browser's camera, once it reported one."""
        if self.client is None:
            return None
        camera = self.client.camera
        try:  # viser asserts that the browser has reported its camera
            width, height = int(camera.image_width), int(camera.image_height)
            if width <= 0 or height <= 0:
                return None
            return CameraView(
                position=np.asarray(camera.position, dtype=np.float64),
                wxyz=np.asarray(camera.wxyz, dtype=np.float64),
                fov=float(camera.fov),
                width=width,
                height=height,
            )
        except (AssertionError, AttributeError, TypeError):
            return None

    def _inside_clip(self, region: RegionBox) -> bool:
        """Whether a region's box reaches into the height clip."""
        low = region.center_local[2] - region.dimensions[2] / 2
        high = region.center_local[2] + region.dimensions[2] / 2
        return high >= self.state.clip_low and low <= self.state.clip_high

    # -- point size ---------------------------------------------------------------------------

    def _point_size(self, name: str) -> float:
        """World size of layer ``name``'s points now."""
        factor = {"unobserved": UNOBSERVED_SIZE_FACTOR}.get(name, 1.0)
        if name in CHANGED_LAYERS:
            factor = CHANGED_SIZE_FACTOR
        return float(self.world_point_size * factor)

    def update_point_size(self, force: bool = False) -> None:
        """Keep points ``point_pixels`` wide on the screen at the camera's target."""
        view = self.camera_view()
        with self.lock:
            if self.state.constant_screen_size and view is not None and self.client is not None:
                distance = float(
                    np.linalg.norm(
                        np.asarray(self.client.camera.position)
                        - np.asarray(self.client.camera.look_at)
                    )
                )
                size = screen_constant_size(
                    self.state.point_pixels, max(distance, 1e-3), view.fov, view.height
                )
                if not force and abs(size - self.world_point_size) <= 0.05 * self.world_point_size:
                    return
                self.world_point_size = size
            for name, handle in self.point_clouds.items():
                handle.point_size = self._point_size(name)

    # -- picking ------------------------------------------------------------------------------

    def pick(self, ray_origin: Sequence[float], ray_direction: Sequence[float]) -> Picked | None:
        """Pick the drawn point under a click; mark it in the scene and show it in the GUI."""
        assert self.data is not None and self.client is not None
        view = self.camera_view()
        pixel_angle = view.fov / view.height if view is not None else 1e-3
        with self.lock:
            visible = {name: self.layer_visible(name) for name in self.rendered}
            picked = pick_point(
                self.data,
                self.rendered,
                visible,
                self.current_labels(),
                np.asarray(ray_origin),
                np.asarray(ray_direction),
                pixel_angle,
                point_radius=self.world_point_size / 2.0,
            )
            self.picked = picked
            if picked is None:
                controls.show_picked(self, None)
                return None
            local = np.asarray(picked.position) - self.data.origin
            self.picked_node = self.client.scene.add_icosphere(
                "/picked",
                radius=max(self.world_point_size * 1.5, 1e-3),
                color=(255, 255, 0),
                position=tuple(local),
                cast_shadow=False,
                receive_shadow=False,
            )
            controls.show_picked(self, picked)
            return picked

    # -- the record ---------------------------------------------------------------------------

    def to_json_dict(self, origin: np.ndarray) -> dict[str, Any]:
        """What viser holds for this client: settings, layers, boxes, labels (file frame)."""
        camera = None
        if self.client is not None:
            camera = {
                "look_at": (np.asarray(self.client.camera.look_at) + origin).tolist(),
                "position": (np.asarray(self.client.camera.position) + origin).tolist(),
                "wxyz": np.asarray(self.client.camera.wxyz, dtype=float).tolist(),
                "fov": float(self.client.camera.fov),
                "image_size": [
                    int(self.client.camera.image_width),
                    int(self.client.camera.image_height),
                ],
            }
        with self.lock:
            return {
                "client_id": self.client_id,
                "camera": camera,
                "state": self.state.to_json_dict(),
                "layers": {
                    name: _layer_record(handle, self.rendered.get(name))
                    for name, handle in self.point_clouds.items()
                },
                "boxes": [_box_record(region, handle, origin) for region, handle in self.boxes],
                "uncertain": [
                    _box_record(box, handle, origin) for box, handle in self.uncertain_nodes
                ],
                "labels": [
                    {
                        "text": handle.text,
                        "kind": kind,
                        "visible": bool(handle.visible),
                        "anchor": handle.anchor,
                        "position": (np.asarray(handle.position) + origin).tolist(),
                    }
                    for kind, handle in [("sensor", node) for node in self.sensor_labels]
                    + [("region", node) for _text, node in self.labels]
                ],
                "moved": [
                    {
                        "removed": pair.removed.index,
                        "added": pair.added.index,
                        "distance": pair.distance,
                        "label": pair.label,
                    }
                    for pair in self.moved
                ],
                "relabelled": self.relabelled is not None,
                "sensors": [
                    {
                        "name": handle.name,
                        "position": (np.asarray(handle.position) + origin).tolist(),
                    }
                    for handle in self.sensor_nodes
                    if isinstance(handle, viser.IcosphereHandle)
                ],
                "picked": None if self.picked is None else self.picked.to_json_dict(),
                "controls": {
                    name: _control_value(handle) for name, handle in self.controls.items()
                },
            }


def screen_constant_size(pixels: float, distance: float, fov: float, height: int) -> float:
    """The world size (metres) viser draws ``pixels`` wide at ``distance`` from the camera.

    viser's shader: ``gl_PointSize = point_size / tan(fov / 2) * height / depth``.
    """
    return float(pixels * distance * math.tan(fov / 2.0) / max(height, 1))


def _digest(layer: RenderedLayer) -> str:
    """A fingerprint of a layer's points and colours (unchanged layers are not resent)."""
    digest = hashlib.blake2b(digest_size=16)
    digest.update(layer.points.tobytes())
    digest.update(layer.colours.tobytes())
    return digest.hexdigest()


def _layer_record(handle: viser.PointCloudHandle, layer: RenderedLayer | None) -> dict[str, Any]:
    """A layer as viser holds it: visibility, point count, size and its colours."""
    colours = np.asarray(handle.colors).reshape(-1, 3)
    n_points = 0 if layer is None else layer.n_points
    unique = np.unique(colours[:n_points], axis=0) if n_points else np.zeros((0, 3))
    return {
        "visible": bool(handle.visible),
        "n_points": n_points,
        "point_size": float(handle.point_size),
        "n_colours": len(unique),
        "mean_colour": colours[:n_points].mean(axis=0).tolist() if n_points else None,
    }


def _box_record(region: RegionBox, handle: Any, origin: np.ndarray) -> dict[str, Any]:
    """A region's outline as viser holds it (file frame)."""
    segments = np.asarray(handle.points, dtype=np.float64).reshape(-1, 2, 3) + origin
    low, high = segments.reshape(-1, 3).min(axis=0), segments.reshape(-1, 3).max(axis=0)
    return {
        "name": handle.name,
        "kind": region.kind,
        "n_points": region.n_points,
        "evidence": region.evidence,
        "visible": bool(handle.visible),
        "colour": np.asarray(handle.colors).reshape(-1, 3)[0].tolist(),
        "center": ((low + high) / 2.0).tolist(),
        "dimensions": (high - low).tolist(),
        "bbox_min": low.tolist(),
        "bbox_max": high.tolist(),
        "n_segments": len(segments),
        "axis_aligned": bool(
            (np.count_nonzero(np.abs(segments[:, 1] - segments[:, 0]) > 1e-6, axis=1) == 1).all()
        ),
    }


def _control_value(handle: Any) -> Any:
    """A GUI control's value (or its content), JSON-ready."""
    for attribute in ("value", "content"):
        if hasattr(handle, attribute):
            value = getattr(handle, attribute)
            if isinstance(value, tuple):
                return list(value)
            return value
    return None


def configure_server(server: viser.ViserServer, data: SceneData, title: str) -> None:
    """Server-wide settings: theme without the share button, up axis, initial camera."""
    server.gui.configure_theme(
        show_share_button=False,  # it calls a tunnel service on the internet
        show_logo=False,
        control_width="medium",
        titlebar_content=None,
    )
    # Docked to the right edge, the panel sits beside the scene: the view opens on the change
    # at the centre of what is seen, not under the panel.
    server.gui.main_panel.dock_right()
    server.scene.set_up_direction(UP_DIRECTION)
    # Points and boxes are flat-coloured: shadow maps only cost time (a lot in software WebGL).
    server.scene.configure_default_lights(enabled=True, cast_shadow=False)
    server.scene.configure_environment_map(hdri=None)  # its PMREM passes are slow in software
    opening = data.opening  # on the change, from its clearest side (or the whole scene)
    server.initial_camera.look_at = tuple(opening.look_at)
    server.initial_camera.position = tuple(opening.position)
    server.initial_camera.near = max(data.extent * 1e-4, 1e-3)
    server.initial_camera.far = max(data.extent * 20.0, 100.0)
    del title


def sensor_marker_radius(data: SceneData) -> float:
    """Radius of a sensor's marker: visible in the whole scene, small next to the rooms."""
    return max(data.extent / 150.0, 0.03)


def draw_sensor_markers(scene: Any, markers: Sequence[SensorMarker], radius: float) -> list[Any]:
    """A sphere in its scan's colour and a label per sensor position; the handles."""
    handles: list[Any] = []
    for number, marker in enumerate(markers):
        colour = STYLE_BY_NAME[marker.side].color
        name = f"/sensors/{marker.side}-{number}"
        handles.append(
            scene.add_icosphere(
                name,
                radius=radius,
                color=colour,
                position=marker.position_local,
                cast_shadow=False,
                receive_shadow=False,
            )
        )
        confidence = "" if marker.confidence is None else f", {marker.confidence:.0%}"
        handles.append(
            scene.add_label(  # a node of its own (not the sphere's child): the declutter moves it
                f"/sensor_labels/{marker.side}-{number}",
                f"{marker.side} sensor ({marker.source}{confidence})",
                position=tuple(np.add(marker.position_local, (0.0, 0.0, radius * 1.5))),
                anchor="bottom-left",
            )
        )
    return handles


def build_client_scene(
    client: viser.ClientHandle, data: SceneData, title: str, box_loader: BoxLoader | None = None
) -> ClientScene:
    """Add layers, region outlines, sensors and the GUI for one browser."""
    record = ClientScene(
        client_id=client.client_id, client=client, data=data, box_loader=box_loader
    )
    record.world_point_size = data.point_size

    # First: a camera the browser reports while the scene is drawn must place the labels.
    @client.camera.on_update
    def _(_camera: Any) -> None:
        record.update_point_size()
        record.declutter()

    @client.scene.on_click()
    def _(event: Any) -> None:
        record.pick(event.ray_origin, event.ray_direction)

    record.sensor_nodes = draw_sensor_markers(
        client.scene, data.sensors, sensor_marker_radius(data)
    ) + draw_trajectory_paths(  # the moving sensors' paths, in their sides' colours
        client.scene,
        data.trajectories,
        {side: STYLE_BY_NAME[side].color for side in ("reference", "scan")},
        sensor_marker_radius(data) / 2,
    )
    with client.atomic():
        controls.add_controls(record, title)
    record.redraw_points()
    record.redraw_regions()
    return record
