"""The 3D view's scene builder and per-job viser servers, on synthetic data (no browser)."""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest

from app.core.datasets.scenes import raycast_scene
from app.viewer.manager import ViewerManager
from app.viewer.scene import (
    LAYER_STYLES,
    allocate_budget,
    build_scene_data,
)


def truth_labels(changed: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """Ground-truth labels: 1 changed, 0 unchanged, -1 unobserved."""
    labels = np.where(changed, 1, 0).astype(np.int8)
    labels[~observed & ~changed] = -1
    return labels


@pytest.fixture(scope="module")
def pair():
    """A small ray-cast rescan with an added, a removed and a moved object."""
    return raycast_scene(n_points=6000, change="mixed", pose_error=(0.05, 1.0), random_state=3)


def georeferenced_regions(offset: np.ndarray) -> list[dict]:
    """Two regions in file coordinates far from the origin."""
    return [
        {
            "id": "r1",
            "kind": "removed",
            "n_points": 40,
            "centroid": (offset + np.array([1.0, 1.0, 0.5])).tolist(),
            "bbox_min": (offset + np.array([0.5, 0.5, 0.0])).tolist(),
            "bbox_max": (offset + np.array([1.5, 1.5, 1.0])).tolist(),
            "mean_distance": 0.3,
            "max_distance": 0.5,
        },
        {
            "id": "r2",
            "kind": "added",
            "n_points": 1,
            "centroid": (offset + np.array([3.0, 2.0, 0.0])).tolist(),
            "bbox_min": (offset + np.array([3.0, 2.0, 0.0])).tolist(),
            "bbox_max": (offset + np.array([3.0, 2.0, 0.0])).tolist(),
            "mean_distance": 0.2,
            "max_distance": 0.2,
        },
    ]


def test_layers_partition_both_clouds_with_scan_in_reference_frame(pair) -> None:
    offset = np.array([512_345.0, 5_412_678.0, 120.0])  # UTM-like: float32 would lose mm
    reference_labels = truth_labels(pair.reference_changed, pair.reference_observed)
    scan_labels = truth_labels(pair.scan_changed, pair.scan_observed)
    shift = np.eye(4)
    shift[:3, 3] = offset
    data = build_scene_data(
        pair.reference + offset,
        pair.scan,  # scan frame: the transform maps it into the georeferenced reference frame
        reference_labels=reference_labels,
        scan_labels=scan_labels,
        transform=shift @ pair.true_transform,
        regions=georeferenced_regions(offset),
    )
    assert [layer.name for layer in data.layers] == [style.name for style in LAYER_STYLES]
    assert data.layer("removed").n_total == int(pair.reference_changed.sum()) > 0
    assert data.layer("added").n_total == int(pair.scan_changed.sum()) > 0
    assert data.n_total == len(pair.reference) + len(pair.scan)
    assert data.n_shown == data.n_total  # under the budget: nothing dropped
    assert data.layer("removed").color == (230, 25, 25)
    assert data.layer("added").color == (20, 200, 50)
    assert not data.layer("unobserved").visible
    for layer in data.layers:
        assert layer.points.dtype == np.float32
    # Local origin: rounded metres near the data; local coordinates are small.
    assert np.allclose(data.origin, np.round(data.origin))
    assert np.abs(data.layer("reference").points).max() < 50.0
    # Added points land where the ground truth says, in the reference frame, to float32 precision.
    expected_added = pair.aligned_scan()[pair.scan_changed] + offset - data.origin
    assert np.allclose(
        np.sort(data.layer("added").points, axis=0), np.sort(expected_added, axis=0), atol=1e-4
    )
    # Region boxes: local centres, real sizes, a minimum edge for single-point regions.
    removed_box, added_box = data.regions
    assert np.allclose(
        np.asarray(removed_box.center_local) + data.origin, offset + np.array([1.0, 1.0, 0.5])
    )
    assert removed_box.dimensions == (1.0, 1.0, 1.0)
    assert min(added_box.dimensions) > 0
    assert removed_box.color == (230, 25, 25) and added_box.color == (20, 200, 50)
    record = data.to_json_dict()
    assert record["regions"][0]["bbox_min"] == (offset + np.array([0.5, 0.5, 0.0])).tolist()
    assert {layer["name"]: layer["shown"] for layer in record["layers"]}["removed"] > 0


def test_large_clouds_are_downsampled_keeping_changed_points(pair) -> None:
    reference_labels = truth_labels(pair.reference_changed, pair.reference_observed)
    scan_labels = truth_labels(pair.scan_changed, pair.scan_observed)
    budget = 2000
    data = build_scene_data(
        pair.reference,
        pair.scan,
        reference_labels=reference_labels,
        scan_labels=scan_labels,
        transform=pair.true_transform,
        point_budget=budget,
    )
    assert data.n_shown <= budget
    assert data.n_total == len(pair.reference) + len(pair.scan)
    changed = data.layer("removed").n_total + data.layer("added").n_total
    assert data.layer("removed").n_shown + data.layer("added").n_shown == min(changed, budget // 2)
    assert data.layer("reference").n_shown < data.layer("reference").n_total


def test_budget_allocation() -> None:
    shown = allocate_budget({"reference": 900, "scan": 900, "removed": 50, "added": 50}, 1000)
    assert shown["removed"] == 50 and shown["added"] == 50
    assert shown["reference"] == shown["scan"] == 450


def test_viewer_manager_binds_loopback_on_its_own_port_and_stops_when_idle(pair) -> None:
    data = build_scene_data(pair.reference[:500], pair.scan[:500])
    manager = ViewerManager(
        lambda job_id: (data, f"job {job_id}"), idle_seconds=0.2, reap_interval=0.1
    )
    try:
        first = manager.get("a")
        second = manager.get("b")
        assert manager.get("a") is first
        assert first.port != second.port and first.port > 0
        with socket.create_connection(("127.0.0.1", first.port), timeout=2):
            pass
        manager.connection_opened("a")
        deadline = time.monotonic() + 5
        while manager.running() != ["a"] and time.monotonic() < deadline:
            time.sleep(0.05)
        assert manager.running() == ["a"]  # b idle and reaped; a has a connection
        manager.connection_closed("a")
        while manager.running() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert manager.running() == []
    finally:
        manager.stop_all()
