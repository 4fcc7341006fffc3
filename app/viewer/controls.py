"""The 3D view's GUI panel for one browser, wired to its
:class:`~app.viewer.viser_scene.ClientScene`.

Summary and quality warnings; the view (before/after, colour mode with its colour bar, the
legend, depth cue, point size, top view); a height clip; the change settings that relabel live;
layer checkboxes; the region list; a box at full density (:mod:`app.viewer.box_controls`); the
picked point and the sensors.  Every control is kept in
``record.controls`` under a short name, so the scene endpoint reports its value.
"""

from __future__ import annotations

import html
import threading
from typing import Any

import numpy as np
import viser

from app.viewer.box_controls import add_box_controls
from app.viewer.colours import colour_bar_html, legend_html
from app.viewer.opening import ASSUMED_ASPECT, CAMERA_FOV, top_view_pose, whole_scene_view
from app.viewer.regions_display import DEFAULT_MOVED_WITHIN, relabel
from app.viewer.rendering import COLOUR_MODES, SHOW_CHOICES, Picked, colour_limit
from app.viewer.scene import MOVED_COLOR, Layer, RegionBox, SceneData
from app.viewer.uncertain_display import UNCERTAIN_COLOUR, uncertain_label

MAX_REGION_BUTTONS = 40
"""Region list length in the GUI; the largest regions are listed first beyond this."""

CEILING_MARGIN = 0.3
""""Cut the ceiling" keeps this much (metres) above the highest region's top (without regions,
the lowest 80 % of the height range)."""


def add_controls(record: Any, title: str) -> None:
    """Build the whole panel for ``record`` (a ClientScene with client and data set)."""
    gui: viser.GuiApi = record.client.gui
    data: SceneData = record.data
    _add_summary(gui, data, title)
    _add_warnings(record, gui, data)
    _add_view_controls(record, gui, data)
    _add_clip_controls(record, gui, data)
    _add_change_controls(record, gui, data)
    _add_layer_controls(record, gui, data)
    _add_region_list(record, gui, data)
    if getattr(record, "box_loader", None) is not None:
        add_box_controls(record, gui, data, record.box_loader)
    with gui.add_folder("Picked point"):
        record.controls["picked"] = gui.add_markdown(
            "Click a point in the scene to read its coordinates, label and distance."
        )
    if data.sensors:
        with gui.add_folder("Sensors", expand_by_default=False):
            lines = [
                f"{marker.side}: {', '.join(f'{value:.2f}' for value in marker.position)} "
                f"({marker.source})"
                for marker in data.sensors
            ]
            record.controls["sensors"] = gui.add_markdown("  \n".join(lines))


def show_picked(record: Any, picked: Picked | None) -> None:
    """Put the picked point (or that nothing was hit) in the panel."""
    handle = record.controls.get("picked")
    if handle is not None:
        handle.content = (
            picked.markdown() if picked is not None else "No point under the cursor; try again."
        )


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


def _add_warnings(record: Any, gui: viser.GuiApi, data: SceneData) -> None:
    """The job's quality warnings, or that there are none."""
    if data.warnings:
        items = "".join(
            f'<li class="scandiff-warning" data-code="{html.escape(item["code"])}">'
            f"{html.escape(item['message'])}</li>"
            for item in data.warnings
        )
        content = (
            '<div class="scandiff-warnings" style="font-size:12px;color:#b35c00;padding:0 0.75em">'
            f"<b>Quality warnings ({len(data.warnings)})</b>"
            f'<ul style="margin:2px 0;padding-left:16px">{items}</ul></div>'
        )
    else:
        content = (
            '<div class="scandiff-warnings" style="font-size:12px;padding:0 0.75em">'
            "No quality warnings.</div>"
        )
    record.controls["warnings"] = gui.add_html(content)


def _add_view_controls(record: Any, gui: viser.GuiApi, data: SceneData) -> None:
    """Before/after, colour mode, colour bar, legend, depth cue, point size, camera buttons."""
    client = record.client
    with gui.add_folder("View"):
        show = gui.add_dropdown(
            "Show", tuple(SHOW_CHOICES.values()), initial_value=SHOW_CHOICES["both"]
        )
        colour = gui.add_dropdown(
            "Colour",
            tuple(COLOUR_MODES.values()) if data.has_distances else (COLOUR_MODES["label"],),
            initial_value=COLOUR_MODES["label"],
            hint="signed distance: reference points negative, scan points positive",
        )
        bar = gui.add_html(colour_bar_html(colour_limit(data)), visible=False)
        legend = gui.add_html(legend_html(_legend_entries(data)))
        depth = gui.add_checkbox(
            "Depth cue", initial_value=True, hint="darken lower points (viser has no eye-dome)"
        )
        constant = gui.add_checkbox("Constant size on screen", initial_value=True)
        size = gui.add_slider("Point size (px)", min=1.0, max=12.0, step=0.5, initial_value=3.0)
        top = gui.add_button("Top view")
        whole = gui.add_button("Whole scene")
    record.controls.update(
        show=show, colour=colour, colour_bar=bar, legend=legend, depth_cue=depth,
        constant_size=constant, point_size=size,
    )  # fmt: skip

    @show.on_update
    def _(event: viser.GuiEvent) -> None:
        choice = {title: key for key, title in SHOW_CHOICES.items()}[event.target.value]
        record.state.show = choice
        record.request_redraw(points=True)

    @colour.on_update
    def _(event: viser.GuiEvent) -> None:
        mode = {title: key for key, title in COLOUR_MODES.items()}[event.target.value]
        record.state.colour_mode = mode
        bar.visible = mode == "distance"
        legend.visible = mode != "distance"  # the colour bar is the legend of distances
        record.request_redraw(points=True)

    @depth.on_update
    def _(event: viser.GuiEvent) -> None:
        record.state.depth_cue = bool(event.target.value)
        record.request_redraw(points=True)

    @constant.on_update
    def _(event: viser.GuiEvent) -> None:
        record.state.constant_screen_size = bool(event.target.value)
        record.update_point_size(force=True)

    @size.on_update
    def _(event: viser.GuiEvent) -> None:
        if not record.state.constant_screen_size:  # world size: scale the current size
            record.world_point_size *= float(event.target.value) / record.state.point_pixels
        record.state.point_pixels = float(event.target.value)
        record.update_point_size(force=True)

    @top.on_click
    def _(_event: viser.GuiEvent) -> None:
        view = record.camera_view()
        position, look_at = top_view_pose(
            data.bounds_min,
            data.bounds_max,
            fov=view.fov if view is not None else CAMERA_FOV,
            aspect=view.width / view.height if view is not None else ASSUMED_ASPECT,
        )
        with client.atomic():  # position first: viser's position setter moves look_at too
            client.camera.position = tuple(position)
            client.camera.look_at = tuple(look_at)

    @whole.on_click
    def _(_event: viser.GuiEvent) -> None:
        view = whole_scene_view(data.bounds_min, data.bounds_max, data.opening.clip_high)
        with client.atomic():
            client.camera.position = tuple(view.position)
            client.camera.look_at = tuple(view.look_at)


def _legend_entries(data: SceneData) -> list[tuple[str, tuple[int, int, int], str]]:
    """Layer colours, the moved colour and the sensors' markers."""
    entries = [(layer.title, layer.color, layer.description) for layer in data.layers]
    entries.append(("Moved", MOVED_COLOR, "a removed and an added region close by"))
    if data.uncertain:
        entries.append(
            ("Uncertain", UNCERTAIN_COLOUR, "dashed: the other scan never covered it (not counted)")
        )
    if data.sensors:
        entries.append(("Sensor", (255, 255, 255), "spheres in the scan's colour"))
    return entries


def _add_clip_controls(record: Any, gui: viser.GuiApi, data: SceneData) -> None:
    """A height range (removes the ceiling or the floor) and two shortcuts, in file heights."""
    offset = float(data.origin[2])
    heights = np.concatenate([side.points[:, 2] for side in data.sides.values()]) + offset
    low = float(np.floor(heights.min() * 10) / 10) if len(heights) else offset - 1.0
    high = float(np.ceil(heights.max() * 10) / 10) if len(heights) else offset + 1.0
    high = max(high, low + 0.1)
    # Indoors, open below the ceiling (it would hide every change); lower when every side of
    # the change is blocked (app.viewer.opening).
    opening_clip = data.opening.clip_high
    opening_top = high
    if np.isfinite(opening_clip):
        opening_top = float(
            np.clip(np.ceil((opening_clip + offset) / 0.05) * 0.05, low + 0.05, high)
        )
    with gui.add_folder("Clip"):
        clip = gui.add_multi_slider(
            "Height (m)",
            min=low,
            max=high,
            step=0.05,
            initial_value=(low, opening_top),
            min_range=0.05,
            hint="z in the reference's frame: only points in the range are drawn"
            + ("; opened cut so nothing hides the change" if opening_top < high else ""),
        )
        ceiling = gui.add_button("Cut the ceiling", hint="keep what lies below the ceiling")
        reset = gui.add_button("No clipping")
    record.controls["clip"] = clip
    record.state.clip_low, record.state.clip_high = low - offset, opening_top - offset

    @clip.on_update
    def _(event: viser.GuiEvent) -> None:
        bottom, top = (float(value) - offset for value in event.target.value)
        record.state.clip_low, record.state.clip_high = bottom, top
        record.request_redraw(points=True, regions=True)

    @ceiling.on_click
    def _(_event: viser.GuiEvent) -> None:
        tops = [r.center_local[2] + r.dimensions[2] / 2 + offset for r in record.regions]
        level = max(tops) + CEILING_MARGIN if tops else low + 0.8 * (high - low)
        level = min(level, high - 0.1)  # always below the highest points: the ceiling's
        clip.value = (low, float(np.clip(round(level / 0.05) * 0.05, low + 0.05, high)))

    @reset.on_click
    def _(_event: viser.GuiEvent) -> None:
        clip.value = (low, high)


def _distance_slider_range(data: SceneData) -> tuple[float, float, float, float]:
    """The distance slider's low, high, step and start: from the candidates' smallest distance
    to the 99.5th percentile of their distances, in steps of a tenth of the job's threshold,
    starting at the threshold (steps of 1 cm from 0 when the job has none)."""
    threshold = data.change_threshold
    floor = min((pool.floor for pool in data.pools.values()), default=0.0)
    far = max(
        (
            float(np.percentile(pool.distances, 99.5))
            for pool in data.pools.values()
            if len(pool.distances)
        ),
        default=0.0,
    )
    step = _nice(threshold / 10.0) if threshold else 0.01
    low = float(np.floor(floor / step) * step) if threshold is not None else 0.0
    high = max(float(np.ceil(far / step) * step), low + 10 * step)
    start = float(np.clip(round((threshold or low) / step) * step, low, high))
    return low, high, step, start


def _add_change_controls(record: Any, gui: viser.GuiApi, data: SceneData) -> None:
    """Distance threshold, minimum region size and moved-pair distance, relabelling live."""
    threshold = data.change_threshold
    enabled = threshold is not None
    low, high, step, start_distance = _distance_slider_range(data)
    lock = threading.Lock()
    with gui.add_folder("Change"):
        distance = gui.add_slider(
            "Min. distance (m)",
            min=low,
            max=high,
            step=step,
            initial_value=start_distance,
            disabled=not enabled,
            hint="a point this far from the other scan's surface is a change candidate",
        )
        size = gui.add_slider(
            "Min. region (pts)",
            min=1,
            max=max(4 * data.min_region_points, 50, *(2 * r.n_points for r in data.regions)),
            step=1,
            initial_value=data.min_region_points,
            disabled=not enabled,
            hint="smaller clusters of candidates are noise",
        )
        moved = gui.add_slider(
            "Moved within (m)",
            min=0.0,
            max=10.0,
            step=0.1,
            initial_value=DEFAULT_MOVED_WITHIN,
            hint="a removed and an added region this close are drawn as one moved object",
        )
        status = gui.add_markdown(_change_status(record, data))
        reset = gui.add_button("The job's result", disabled=not enabled)
    record.controls.update(
        min_distance=distance, min_region_points=size, moved_within=moved, change_status=status
    )
    record.state.moved_within = DEFAULT_MOVED_WITHIN
    resetting = threading.Event()

    def apply(_event: viser.GuiEvent) -> None:
        if resetting.is_set() or not enabled:
            return
        with lock:
            # the slider's start is the job's threshold rounded to a step: it means the threshold
            untouched = distance.value == start_distance and threshold is not None
            min_distance = float(threshold if untouched else distance.value)  # type: ignore[arg-type]
            record.state.min_distance = min_distance
            record.state.min_region_points = int(size.value)
            # the scene drawn now: the job's whole view, or a box of it at full density
            record.relabelled = relabel(record.data, min_distance, int(size.value))
            record.request_redraw(points=True, regions=True)

    distance.on_update(apply)
    size.on_update(apply)

    @moved.on_update
    def _(event: viser.GuiEvent) -> None:
        record.state.moved_within = float(event.target.value)
        record.request_redraw(regions=True)

    @reset.on_click
    def _(_event: viser.GuiEvent) -> None:
        with lock:
            resetting.set()
            try:
                distance.value = start_distance
                size.value = data.min_region_points
            finally:
                resetting.clear()
            record.state.min_distance = record.state.min_region_points = None
            record.relabelled = None
            record.request_redraw(points=True, regions=True)


def refresh_change_status(record: Any) -> None:
    """Say in the panel how many regions are drawn (after each redraw of the regions)."""
    handle = record.controls.get("change_status")
    if handle is not None:
        handle.content = _change_status(record, record.data)


def _change_status(record: Any, data: SceneData) -> str:
    """How many regions are drawn and whether they are the job's."""
    regions = record.regions if record.data is not None else data.regions
    counts = {kind: sum(r.kind == kind for r in regions) for kind in ("removed", "added")}
    moved = len(record.moved)
    text = (
        f"**{len(regions)} regions** ({counts['removed']} removed, {counts['added']} added"
        + (f"; {moved} moved pair{'s' if moved != 1 else ''}" if moved else "")
        + ")"
    )
    if record.relabelled is not None:
        approximate = (
            data.change_threshold is not None
            and record.relabelled.min_distance < data.change_threshold
        )
        how = (
            "below the job's threshold: distances only, no visibility test"
            if approximate
            else "from the job's changed points"
        )
        return text + f"  \nrelabelled live ({how}); the job found {len(data.regions)}"
    if data.change_threshold is None:
        return text + "  \nthis job stored no distances: the sliders are off"
    return text + "  \nthe job's result"


def _add_layer_controls(record: Any, gui: viser.GuiApi, data: SceneData) -> None:
    """A checkbox per layer and one for the region outlines."""
    with gui.add_folder("Layers", expand_by_default=False):
        for layer in data.layers:
            checkbox = gui.add_checkbox(
                _layer_label(layer),
                initial_value=layer.visible and layer.n_shown > 0,
                disabled=layer.n_shown == 0,
                hint=f"{layer.description}: {layer.n_shown:,} shown of {layer.n_total:,}",
            )
            record.state.layer_visible[layer.name] = layer.visible
            checkbox.on_update(_visibility_toggle(record, layer.name))
        boxes = gui.add_checkbox(
            f"Region boxes ({len(data.regions)})", initial_value=True, disabled=not data.regions
        )
        uncertain = gui.add_checkbox(
            f"Uncertain regions ({len(data.uncertain)})",
            initial_value=bool(data.uncertain),
            disabled=not data.uncertain,
            hint="grey dashed boxes: places the other scan never covered, not counted as change",
        )
    record.controls["uncertain_regions"] = uncertain

    @boxes.on_update
    def _(event: viser.GuiEvent) -> None:
        record.boxes_visible = bool(event.target.value)
        record.request_redraw(regions=True)

    @uncertain.on_update
    def _(event: viser.GuiEvent) -> None:
        record.uncertain_visible = bool(event.target.value)
        record.request_redraw(regions=True)


def _visibility_toggle(record: Any, name: str) -> Any:
    """A checkbox handler that shows or hides layer ``name``."""

    def toggle(event: viser.GuiEvent) -> None:
        record.state.layer_visible[name] = bool(event.target.value)
        handle = record.point_clouds.get(name)
        if handle is not None:
            handle.visible = record.layer_visible(name)

    return toggle


def _add_region_list(record: Any, gui: viser.GuiApi, data: SceneData) -> None:
    """One button per region (the job's) that moves this browser's camera to it."""
    regions = sorted(data.regions, key=lambda region: -region.n_points)[:MAX_REGION_BUTTONS]
    with gui.add_folder(f"Regions ({len(data.regions)})", expand_by_default=bool(regions)):
        if not data.regions:
            gui.add_markdown("No changed regions.")
        elif len(data.regions) > len(regions):
            gui.add_markdown(f"The {len(regions)} largest of {len(data.regions)} are listed.")
        for region in regions:
            button = gui.add_button(
                region.label,
                color="red" if region.kind == "removed" else "green",
                hint=f"centroid {', '.join(f'{value:.2f}' for value in region.centroid)}",
            )
            button.on_click(_camera_mover(record.client, region))
        _add_uncertain_list(record, gui, data)


def _add_uncertain_list(record: Any, gui: viser.GuiApi, data: SceneData) -> None:
    """The uncertain regions under the region buttons, grey, each with its evidence."""
    if not data.uncertain:
        return
    listed = sorted(data.uncertain, key=lambda box: -box.n_points)[:MAX_REGION_BUTTONS]
    record.controls["uncertain_list"] = gui.add_markdown(
        f"**Uncertain ({len(data.uncertain)})**: the other scan never covered these places; "
        "listed, not counted as change"
        + (f" (the {len(listed)} largest)" if len(listed) < len(data.uncertain) else "")
    )
    for box in listed:
        button = gui.add_button(
            uncertain_label(box),
            color="gray",
            hint=f"centroid {', '.join(f'{value:.2f}' for value in box.centroid)}",
        )
        button.on_click(_camera_mover(record.client, box))


def _camera_mover(client: viser.ClientHandle, region: RegionBox) -> Any:
    """A click handler that frames ``region`` from the camera's current direction."""
    lock = threading.Lock()

    def move(_event: viser.GuiEvent) -> None:
        with lock:
            center = np.asarray(region.center_local, dtype=np.float64)
            direction = np.asarray(client.camera.position) - np.asarray(client.camera.look_at)
            norm = float(np.linalg.norm(direction))
            direction = direction / norm if norm > 1e-9 else np.array([-0.55, -0.75, 0.55])
            distance = max(float(np.linalg.norm(region.dimensions)) * 2.0, 1.0)
            with client.atomic():  # position first: viser's position setter moves look_at too
                client.camera.position = tuple(center + direction * distance)
                client.camera.look_at = tuple(center)

    return move


def _layer_label(layer: Layer) -> str:
    """Checkbox text: title and shown/total counts."""
    if layer.n_shown == layer.n_total:
        return f"{layer.title} ({layer.n_total:,})"
    return f"{layer.title} ({layer.n_shown:,}/{layer.n_total:,})"


def _nice(value: float) -> float:
    """``value`` rounded down to 1, 2 or 5 times a power of ten (at least 1 mm)."""
    value = max(float(value), 1e-3)
    power = 10.0 ** np.floor(np.log10(value))
    for factor in (5.0, 2.0, 1.0):
        if value >= factor * power:
            return float(factor * power)
    return float(power)
