"""The 3D view's review tools on a real comparison, without a browser: colours, live
relabelling, moved pairs, box outlines, label declutter, picking, sensor markers, warnings."""

from __future__ import annotations

import math
import time
from types import SimpleNamespace

import numpy as np
import pytest
import viser

from app.core.datasets.scenes import raycast_scene
from app.testing.viewer_scenes import compare_with_origins, scene_of
from app.viewer.colours import (
    NO_DISTANCE_COLOUR,
    colour_bar_html,
    shade_by_height,
    signed_distance_colours,
)
from app.viewer.loading import job_sensor_origins, job_warnings
from app.viewer.regions_display import (
    CameraView,
    box_edges,
    declutter,
    pair_moved,
    relabel,
)
from app.viewer.rendering import PICK_PIXELS, ViewState, pick_point, render_layers
from app.viewer.scene import RegionBox, build_scene_data
from app.viewer.viser_scene import draw_sensor_markers, screen_constant_size


@pytest.fixture(scope="module")
def job():
    """A ray-cast rescan with an added, a removed and a moved box, compared like the worker."""
    pair = raycast_scene(n_points=8000, change="mixed", pose_error=(0.02, 0.3), random_state=7)
    result = compare_with_origins(pair)
    data = scene_of(pair, result)
    return SimpleNamespace(pair=pair, result=result, data=data)


def test_signed_distance_colours_run_from_removed_red_to_added_green() -> None:
    colours = signed_distance_colours(np.array([-1.0, -0.01, 0.0, 0.01, 1.0, np.nan]), 0.5)
    removed, near_minus, zero, near_plus, added, unknown = colours.astype(int)
    assert removed[0] > 150 > removed[1] and added[1] > 100 > added[0]
    assert abs(zero[0] - zero[1]) < 5 and zero[0] > 150  # neutral grey at zero
    assert np.abs(near_minus - zero).max() < 10 and np.abs(near_plus - zero).max() < 10
    assert tuple(unknown) == NO_DISTANCE_COLOUR
    shaded = shade_by_height(np.array([200, 100, 50], np.uint8), np.array([0.0, 1.0, 2.0]), 0, 2)
    assert shaded[0].sum() < shaded[1].sum() < shaded[2].sum() and tuple(shaded[2]) == (
        200,
        100,
        50,
    )
    assert 'data-limit="0.25"' in colour_bar_html(0.25)


def test_layers_by_distance_before_after_and_height_clip(job) -> None:
    data = job.data
    labels = {side: data.sides[side].labels for side in data.sides}
    by_label = render_layers(data, ViewState(depth_cue=False), labels)
    assert {tuple(c) for c in by_label["removed"].colours} == {(230, 25, 25)}
    assert by_label["reference"].colours[0].tolist() != by_label["scan"].colours[0].tolist()
    by_distance = render_layers(data, ViewState(colour_mode="distance", depth_cue=False), labels)
    removed = by_distance["removed"].colours.astype(float).mean(axis=0)
    added = by_distance["added"].colours.astype(float).mean(axis=0)
    assert removed[0] > removed[1] and added[1] > added[0]
    assert len(np.unique(by_distance["reference"].colours, axis=0)) > 10
    before = render_layers(data, ViewState(show="reference"), labels)
    assert before["scan"].n_points == before["added"].n_points == 0
    assert before["reference"].n_points == by_label["reference"].n_points
    clipped = render_layers(data, ViewState(clip_high=0.0), labels)
    for name, layer in clipped.items():
        assert (layer.points[:, 2] <= 0.0).all()
        assert layer.n_points <= by_label[name].n_points
    assert clipped["reference"].n_points < by_label["reference"].n_points


def test_relabelling_reproduces_the_job_and_tightens_live(job) -> None:
    data, result = job.data, job.result
    same = relabel(data, data.change_threshold, data.min_region_points)
    assert sorted(r.n_points for r in same.regions) == sorted(r.n_points for r in data.regions)
    for side, labels in (("reference", result.reference_label), ("scan", result.scan_label)):
        np.testing.assert_array_equal(same.changed_rows[side], np.flatnonzero(labels == 1))
    largest = max(region.n_points for region in data.regions)
    only_largest = relabel(data, data.change_threshold, largest)
    assert [region.n_points for region in only_largest.regions] == [largest]
    farther = relabel(data, data.change_threshold * 2, data.min_region_points)
    assert sum(map(len, farther.changed_rows.values())) < sum(map(len, same.changed_rows.values()))
    side = data.sides["reference"]
    relabelled = only_largest.labels_of(side)
    assert ((relabelled == 1) <= (side.labels == 1)).all()  # stricter: a subset
    assert ((relabelled == -1) == (side.labels == -1)).all()  # unobserved stays unobserved


def region(index: int, kind: str, center: tuple, size: tuple = (0.8, 0.6, 0.8)) -> RegionBox:
    """A region box for the pairing tests."""
    return RegionBox(
        index=index,
        region_id=None,
        kind=kind,
        n_points=100,
        centroid=center,
        bbox_min=tuple(np.subtract(center, np.divide(size, 2))),
        bbox_max=tuple(np.add(center, np.divide(size, 2))),
        center_local=center,
        dimensions=size,
        mean_distance=0.3,
        max_distance=0.5,
    )


def test_removed_and_added_close_by_pair_into_moved_objects() -> None:
    regions = [
        region(0, "removed", (0.0, 0.0, 0.4)),
        region(1, "added", (0.5, 0.0, 0.4)),
        region(2, "added", (0.9, 0.0, 0.4)),
        region(3, "removed", (10.0, 0.0, 0.4)),
        region(4, "added", (10.3, 0.0, 0.4), size=(3.0, 3.0, 3.0)),  # close, another size
    ]
    pairs = pair_moved(regions, within=1.0)
    assert [(p.removed.index, p.added.index) for p in pairs] == [(0, 1)]
    assert math.isclose(pairs[0].distance, 0.5) and "moved 0.50 m" in pairs[0].label
    assert pair_moved(regions, within=0.4) == ()


def test_box_outlines_are_twelve_axis_aligned_edges() -> None:
    edges = box_edges((1.0, 2.0, 3.0), (2.0, 4.0, 6.0))
    assert edges.shape == (12, 2, 3)
    differing = np.count_nonzero(np.abs(edges[:, 1] - edges[:, 0]) > 1e-6, axis=1)
    assert (differing == 1).all()  # no diagonal
    corners = np.unique(edges.reshape(-1, 3), axis=0)
    assert len(corners) == 8
    np.testing.assert_allclose(corners.min(axis=0), (0.0, 0.0, 0.0))
    np.testing.assert_allclose(corners.max(axis=0), (2.0, 4.0, 6.0))


def test_labels_that_would_overlap_on_screen_are_dropped() -> None:
    camera = CameraView(
        position=np.array([0.0, 0.0, -10.0]),
        wxyz=np.array([1.0, 0.0, 0.0, 0.0]),  # OpenCV: looking along +z
        fov=math.radians(60),
        width=800,
        height=600,
    )
    anchors = np.array([[0.0, 0.0, 0.0]] * 5 + [[3.0, 3.0, 0.0], [0.0, 0.0, -20.0]])
    texts = [f"#{number} added" for number in range(1, 8)]
    placed = declutter(anchors, texts, camera, 0.5)
    # five labels at one point: four places around it, then none; the last is behind
    assert placed == [
        "bottom-left", "top-left", "bottom-right", "top-right", None, "bottom-left", None
    ]  # fmt: skip
    pixels, in_front = camera.project(anchors[:1])
    np.testing.assert_allclose(pixels[0], (400.0, 300.0))
    assert in_front[0]
    world = declutter(anchors[4:6], texts[4:6], None, world_separation=0.5)
    assert world == ["bottom-left", "bottom-left"]
    assert declutter(anchors[:2], texts[:2], None, world_separation=0.5) == ["bottom-left", None]


def test_a_click_picks_the_nearest_drawn_point_on_its_ray(job) -> None:
    data = job.data
    labels = {side: data.sides[side].labels for side in data.sides}
    layers = render_layers(data, ViewState(), labels)
    visible = {name: True for name in layers}
    removed = layers["removed"]
    target = removed.points[len(removed.points) // 2].astype(float)
    camera = target + np.array([0.0, 0.0, 3.0])  # from above: the top point on the ray wins
    angle = math.radians(0.02)
    picked = pick_point(data, layers, visible, labels, camera, target - camera, angle)
    assert picked is not None
    local = np.asarray(picked.position) - data.origin
    tolerance = 3.0 * math.tan(angle * PICK_PIXELS)
    assert np.linalg.norm((local - target)[:2]) <= tolerance and local[2] >= target[2] - 1e-4
    if picked.layer == "removed":
        assert picked.label_name == "removed" and picked.distance < 0
        stored = job.result.reference_distance[picked.row]
        assert math.isclose(-picked.distance, stored, rel_tol=1e-6)
    miss = pick_point(
        data, layers, visible, labels, camera, np.array([0.0, 0.0, 1.0]), math.radians(0.05)
    )
    assert miss is None  # pointing up, away from every point


def test_sensor_markers_and_warnings_read_from_the_job_row() -> None:
    row = SimpleNamespace(
        sensor_origins={
            "reference": [{"origin": [104.6, 203.6, 11.2], "source": "given", "confidence": 1.0}],
            "scan": [
                {"origin": [1.0, 0.0, 0.0], "source": "estimated", "confidence": 0.8},
                {"origin": "not a point", "source": "file"},
            ],
        },
        warnings=[{"code": "low_overlap", "message": "only 30 % of the scan overlaps"}, "junk"],
    )
    empty = SimpleNamespace(sensor_origins=None, warnings=None)  # a job stored before 0008
    assert job_sensor_origins(empty) == {} and job_warnings(empty) == []
    shift = np.eye(4)
    shift[:3, 3] = (100.0, 200.0, 10.0)
    rng = np.random.default_rng(0)
    data = build_scene_data(
        rng.uniform(0, 5, (500, 3)) + np.array([100.0, 200.0, 10.0]),
        rng.uniform(0, 5, (500, 3)),
        transform=shift,
        sensor_origins=job_sensor_origins(row),
        warnings=job_warnings(row),
    )
    assert [(m.side, m.source) for m in data.sensors] == [
        ("reference", "given"),
        ("scan", "estimated"),
    ]
    np.testing.assert_allclose(data.sensors[1].position, (101.0, 200.0, 10.0))  # moved by shift
    assert data.to_json_dict()["warnings"] == [
        {"code": "low_overlap", "message": "only 30 % of the scan overlaps"}
    ]
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        handles = draw_sensor_markers(server.scene, data.sensors, radius=0.1)
        spheres = [h for h in handles if isinstance(h, viser.IcosphereHandle)]
        labels = [h for h in handles if isinstance(h, viser.LabelHandle)]
        assert [h.name for h in spheres] == ["/sensors/reference-0", "/sensors/scan-1"]
        for sphere, marker in zip(spheres, data.sensors, strict=True):
            np.testing.assert_allclose(
                np.asarray(sphere.position) + data.origin, marker.position, atol=1e-6
            )
        assert tuple(spheres[0].color) != tuple(spheres[1].color)
        assert "scan sensor (estimated, 80%)" in [label.text for label in labels]
    finally:
        server.stop()
        time.sleep(0.1)


def test_constant_screen_size_inverts_visers_point_shader() -> None:
    fov, height = math.radians(50), 860
    for distance in (0.5, 5.0, 50.0):
        size = screen_constant_size(3.0, distance, fov, height)
        pixels = size / math.tan(fov / 2) * height / distance  # viser's gl_PointSize
        assert math.isclose(pixels, 3.0)


def test_a_job_without_stored_distances_keeps_its_labels_and_turns_the_sliders_off(job) -> None:
    pair, result = job.pair, job.result
    data = build_scene_data(
        pair.reference,
        pair.scan,
        reference_labels=result.reference_label,
        scan_labels=result.scan_label,
        transform=result.registration.transform,
        regions=result.to_json_dict()["regions"],
    )
    assert not data.has_distances and data.change_threshold is None
    assert all(len(pool.indices) == 0 for pool in data.pools.values())
    labels = {side: data.sides[side].labels for side in data.sides}
    layers = render_layers(data, ViewState(colour_mode="distance", depth_cue=False), labels)
    assert layers["removed"].n_points == job.data.layer("removed").n_shown
    assert {tuple(colour) for colour in layers["removed"].colours} == {NO_DISTANCE_COLOUR}
