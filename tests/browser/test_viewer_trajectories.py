"""The 3D view draws each moving sensor's path (no browser): a polyline per side.

Rules checked: a job's ``sensor_origins`` entries with ``"source": "trajectory"`` become paths
in the scene's local frame, the scan's moved by the registration like its points; malformed
entries and other origins draw no path; each path is drawn as viser line segments in its side's
colour.
"""

from __future__ import annotations

import time

import numpy as np
import viser

from app.viewer.scene import STYLE_BY_NAME, build_scene_data
from app.viewer.trajectory_display import draw_trajectory_paths

OFFSET = np.array([100.0, 200.0, 10.0])


def test_trajectory_paths_are_drawn_per_side_in_the_reference_frame() -> None:
    path = [[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [2.0, 1.0, 1.0]]
    sensor_origins = {
        "reference": [
            {"source": "trajectory", "poses": 3, "path": (np.array(path) + OFFSET).tolist()}
        ],
        "scan": [
            {"source": "trajectory", "poses": 3, "path": path},
            {"source": "trajectory", "path": "not a path"},
            {"origin": [1.0, 0.0, 0.0], "source": "estimated", "confidence": 0.8},
        ],
    }
    shift = np.eye(4)
    shift[:3, 3] = OFFSET
    rng = np.random.default_rng(0)
    data = build_scene_data(
        rng.uniform(0, 5, (500, 3)) + OFFSET,
        rng.uniform(0, 5, (500, 3)),
        transform=shift,
        sensor_origins=sensor_origins,
    )

    assert [trajectory.side for trajectory in data.trajectories] == ["reference", "scan"]
    for trajectory in data.trajectories:  # the scan's path moved by the registration
        np.testing.assert_allclose(
            trajectory.positions_local + data.origin, np.array(path) + OFFSET, atol=1e-5
        )
    assert [marker.source for marker in data.sensors] == ["estimated"]
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        colours = {side: STYLE_BY_NAME[side].color for side in ("reference", "scan")}
        handles = draw_trajectory_paths(server.scene, data.trajectories, colours, thickness=0.05)
        assert [handle.name for handle in handles] == [
            "/trajectories/reference-0",
            "/trajectories/scan-1",
        ]
        assert np.asarray(handles[0].points).shape == (2, 2, 3)  # two segments
        assert tuple(np.asarray(handles[1].colors).reshape(-1, 3)[0]) == STYLE_BY_NAME["scan"].color
    finally:
        server.stop()
        time.sleep(0.1)
