"""The 3D view's "Full density in a box" panel: one box of the scene drawn at full density.

A large job opens at the point budget (strided, changed points first); the panel reads the
points inside a box of the reference frame from the files at full density, up to the budget
(:func:`app.viewer.loading.load_job_box`), and draws them instead of the whole view, until
"Back to the whole view". When the box holds more points than the budget, the panel says so.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import numpy as np
import viser
from numpy.typing import NDArray

from app.viewer.scene import SceneData

BoxLoader = Callable[[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]], SceneData]
"""``(low, high, origin) -> scene``: the job's points in a box (file coordinates of the
reference frame), with the view's local origin."""

BOX_MARGIN = 1.0
"""The box offered first is the regions' box grown by this much (metres) on every side."""


def initial_box(data: SceneData) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The box offered first (file coordinates): around the regions, else the drawn bounds."""
    if data.regions:
        low = np.min([region.bbox_min for region in data.regions], axis=0) - BOX_MARGIN
        high = np.max([region.bbox_max for region in data.regions], axis=0) + BOX_MARGIN
        return low, high
    return data.bounds_min + data.origin, data.bounds_max + data.origin


def box_status(data: SceneData) -> str:
    """What the panel says of a box's scene: all of it at full density, or capped."""
    capped = [warning for warning in data.warnings if warning.get("code") == "box_capped"]
    if capped:
        return f"**Capped by the point budget**: {capped[0]['message']}."
    return f"All **{data.n_total:,}** points in the box, at full density."


def add_box_controls(record: Any, gui: viser.GuiApi, whole: SceneData, loader: BoxLoader) -> None:
    """The panel's folder for ``record`` (a ClientScene): two corners, load and back buttons."""
    low, high = initial_box(whole)
    with gui.add_folder("Full density in a box", expand_by_default=False):
        low_input = gui.add_vector3("Low corner", initial_value=tuple(low), step=0.1)
        high_input = gui.add_vector3("High corner", initial_value=tuple(high), step=0.1)
        load = gui.add_button("Load the box at full density")
        back = gui.add_button("Back to the whole view", disabled=True)
        status = gui.add_markdown(
            f"The whole view shows {whole.n_shown:,} of {whole.n_total:,} points."
        )
    record.controls.update(box_low=low_input, box_high=high_input, box_status=status)
    loading = threading.Lock()

    @load.on_click
    def _(_event: viser.GuiEvent) -> None:
        if not loading.acquire(blocking=False):
            return
        try:
            status.content = "Reading the box from the files..."
            corners = np.asarray(low_input.value, float), np.asarray(high_input.value, float)
            try:
                box = loader(*corners, whole.origin)
            except Exception as exc:  # a malformed box (ViewUnavailableError), a missing file
                status.content = f"Cannot load the box: {getattr(exc, 'message', exc)}"
                return
            show_scene(record, box)
            back.disabled = False
            status.content = box_status(box)
        finally:
            loading.release()

    @back.on_click
    def _(_event: viser.GuiEvent) -> None:
        show_scene(record, whole)
        back.disabled = True
        status.content = f"The whole view shows {whole.n_shown:,} of {whole.n_total:,} points."


def show_scene(record: Any, data: SceneData) -> None:
    """Draw ``data`` (same origin) instead of the record's scene, the job's own labels."""
    with record.lock:
        record.data = data
        record.relabelled = None
        record.picked = None
    record.request_redraw(points=True, regions=True)
