"""Where the 3D view opens (issue 31), without a browser: the camera frames the change from the
side where nothing hides it, cuts a closed box open, frames the whole scene without change; the
top view fills the canvas; labels (sensors included) never overlap, nor sit on another box."""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from app.viewer.opening import (
    CAMERA_FOV,
    choose_opening_view,
    top_view_pose,
    whole_scene_view,
)
from app.viewer.regions_display import CameraView, declutter, label_box, screen_box

WIDTH, HEIGHT = 1280, 800


def grid(low: tuple[float, float, float], high: tuple[float, float, float], step: float):
    """Points every ``step`` metres on the axis-aligned box ``low``-``high`` (a flat box is a
    plane patch)."""
    axes = [
        np.arange(a, b + 1e-9, step) if b > a else np.array([a])
        for a, b in zip(low, high, strict=True)
    ]
    mesh = np.meshgrid(*axes, indexing="ij")
    return np.column_stack([axis.ravel() for axis in mesh])


def looking(position: np.ndarray, target: np.ndarray) -> CameraView:
    """A camera at ``position`` looking at ``target`` with z up (viser's OpenCV convention:
    x right, y down, z forward), at 1280 x 800 with viser's field of view."""
    forward = (target - position) / np.linalg.norm(target - position)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    x, y, z, w = Rotation.from_matrix(np.column_stack([right, down, forward])).as_quat()
    return CameraView(position, np.array([w, x, y, z]), CAMERA_FOV, WIDTH, HEIGHT)


def hidden_share(occluders: np.ndarray, camera: np.ndarray, targets: np.ndarray) -> float:
    """Share of ``targets`` with an occluder within 10 cm of the line of sight from ``camera``
    (ignoring the last 40 cm), by brute force: the check is independent of the grid."""
    blocked = 0
    for target in targets:
        offset = target - camera
        length = np.linalg.norm(offset)
        along = (occluders - camera) @ offset / length
        across = np.linalg.norm(np.cross(occluders - camera, offset / length), axis=1)
        blocked += bool(np.any((along > 0) & (along < length - 0.4) & (across < 0.1)))
    return blocked / len(targets)


def walled_yard() -> tuple[np.ndarray, np.ndarray]:
    """A 20 x 20 m floor, a 3 m wall along y = 0 and a 1 m box 2 m north of it (the change)."""
    floor = grid((-10, -10, 0), (10, 10, 0), 0.2)
    wall = grid((-10, 0, 0), (10, 0, 3), 0.1)
    box = np.vstack(
        [grid((-0.5, 1.5, z), (0.5, 2.5, z), 0.1) for z in (0.0, 1.0)]
        + [grid((x, 1.5, 0), (x, 2.5, 1), 0.1) for x in (-0.5, 0.5)]
        + [grid((-0.5, y, 0), (0.5, y, 1), 0.1) for y in (1.5, 2.5)]
    )
    floor = floor[~((np.abs(floor[:, 0]) <= 0.5) & (np.abs(floor[:, 1] - 2) <= 0.5))]
    return np.vstack([floor, wall]), box


def test_a_change_behind_a_wall_is_seen_from_its_open_side() -> None:
    unchanged, changed = walled_yard()
    low, high = unchanged.min(axis=0), unchanged.max(axis=0)
    view = choose_opening_view(unchanged, changed, low, high)
    assert view.reason == "change"
    assert np.allclose(view.look_at, [0.0, 2.0, 0.5], atol=0.1)
    sample = changed[:: max(len(changed) // 100, 1)]
    assert hidden_share(unchanged, view.position, sample) <= 0.1
    assert view.blocked_share is not None and view.blocked_share <= 0.1
    # the old whole-scene view, from the south-west, sees the box through the wall
    old = whole_scene_view(low, high, math.inf)
    assert hidden_share(unchanged, old.position, sample) >= 0.9
    # framed: every changed point lies on the 1280 x 800 screen
    pixels, in_front = looking(view.position, view.look_at).project(changed)
    assert in_front.all()
    assert (pixels >= 0).all() and (pixels[:, 0] <= WIDTH).all() and (pixels[:, 1] <= HEIGHT).all()


def test_a_change_in_a_closed_crate_opens_cut_above_it() -> None:
    floor = grid((-10, -10, 0), (10, 10, 0), 0.2)
    crate = np.vstack(
        [grid((-1.5, -1.5, 2.0), (1.5, 1.5, 2.0), 0.1)]  # lid
        + [grid((x, -1.5, 0), (x, 1.5, 2), 0.1) for x in (-1.5, 1.5)]
        + [grid((-1.5, y, 0), (1.5, y, 2), 0.1) for y in (-1.5, 1.5)]
    )
    changed = grid((-0.3, -0.3, 0.0), (0.3, 0.3, 0.6), 0.1)
    unchanged = np.vstack([floor, crate])
    low, high = unchanged.min(axis=0), unchanged.max(axis=0)
    view = choose_opening_view(unchanged, changed, low, high)
    assert view.reason == "change, cut above it"
    assert 0.6 < view.clip_high < 2.0  # above the change, below the lid
    kept = unchanged[unchanged[:, 2] <= view.clip_high]
    assert hidden_share(kept, view.position, changed[::3]) <= 0.2


def test_without_change_the_whole_scene_is_framed() -> None:
    unchanged, _changed = walled_yard()
    low, high = unchanged.min(axis=0), unchanged.max(axis=0)
    view = choose_opening_view(unchanged, np.zeros((0, 3)), low, high)
    assert view.reason == "whole scene" and view.blocked_share is None
    assert np.allclose(view.look_at, (low + high) / 2)


def test_the_top_view_fills_the_canvas() -> None:
    for low, high in (
        ((0, 0, 0), (16, 8, 3)),
        ((0, 0, 0), (8, 30, 3)),
        ((-60, -40, -2), (60, 40, 3)),
    ):
        low, high = np.array(low, float), np.array(high, float)
        position, look_at = top_view_pose(low, high, CAMERA_FOV, WIDTH / HEIGHT)
        camera = looking(position, look_at)
        middle = (low[2] + high[2]) / 2
        corners = np.array([[x, y, middle] for x in (low[0], high[0]) for y in (low[1], high[1])])
        pixels, in_front = camera.project(corners)
        assert in_front.all()
        assert (pixels >= -1).all() and (pixels[:, 0] <= WIDTH + 1).all()
        assert (pixels[:, 1] <= HEIGHT + 1).all()
        width, height = np.ptp(pixels[:, 0]), np.ptp(pixels[:, 1])
        assert width >= 0.9 * WIDTH or height >= 0.9 * HEIGHT, (width, height)
        assert width >= height  # the longer side runs across the wider screen axis


def boxes_overlap(first: tuple[float, ...], second: tuple[float, ...]) -> bool:
    """Whether two screen boxes (left, top, right, bottom) overlap."""
    return (
        first[0] < second[2]
        and second[0] < first[2]
        and first[1] < second[3]
        and second[1] < first[3]
    )


def test_sensor_and_region_labels_never_overlap_nor_cover_another_box() -> None:
    camera = looking(np.array([0.0, -12.0, 8.0]), np.array([0.0, 0.0, 0.0]))
    texts = [
        "reference sensor (file)",
        "scan sensor (estimated, 80%)",
        "#1 removed",
        "#2 added",
    ]
    anchors = np.array(
        [[0.0, 0.0, 1.5], [0.05, 0.0, 1.5], [0.1, 0.0, 1.4], [2.0, 0.0, 0.8]]
    )  # both sensors and a region's corner at almost the same pixel
    placed = declutter(anchors, texts, camera, world_separation=0.5, placed_together=2)
    assert placed[0] is not None and placed[1] is not None  # both sensors keep their labels
    pixels, _ = camera.project(anchors)
    shown = [label_box(pixels[i], texts[i], placed[i]) for i in range(4) if placed[i]]
    for index, box in enumerate(shown):
        assert not any(boxes_overlap(box, other) for other in shown[:index]), shown
    # the blocked case of one-by-one placement: the second sensor's point lies inside the first
    # sensor's label (just right of and above its point); placed together, both are shown
    pixel = camera.project(anchors[:1])[0][0]
    nearby = anchors[0] + np.array([0.3, 0.0, 0.05])
    near_pixel = camera.project(nearby[None])[0][0]
    assert 0 < near_pixel[0] - pixel[0] < 100 and -18 < near_pixel[1] - pixel[1] < 0
    pair = np.vstack([anchors[0], nearby])
    assert declutter(pair, texts[:2], camera, 0.5)[1] is None  # one by one: hidden
    together = declutter(pair, texts[:2], camera, 0.5, placed_together=2)
    assert None not in together
    pair_pixels, _ = camera.project(pair)
    first, second = (label_box(pair_pixels[i], texts[i], together[i]) for i in range(2))
    assert not boxes_overlap(first, second)
    # a region's label moves off another region's box when an anchor is free of it
    other = screen_box(camera, (2.6, 0.0, 1.5), (1.0, 1.0, 1.0))  # above-right of #2's corner
    assert other is not None
    assert boxes_overlap(label_box(pixels[3], texts[3], "bottom-left"), other)
    alone = declutter(anchors[3:], texts[3:], camera, 0.5, obstacles=[[other]])
    assert alone[0] is not None
    assert not boxes_overlap(label_box(pixels[3], texts[3], alone[0]), other)


def test_a_thin_change_is_not_looked_at_edge_on() -> None:
    floor = grid((-10, -10, 0), (10, 10, 0), 0.2)
    face = grid((2.0, -1.0, 0.0), (2.0, 1.0, 1.2), 0.05)  # a box's one face a lidar saw
    view = choose_opening_view(floor, face, floor.min(axis=0), np.array([10.0, 10.0, 3.0]))
    direction = (view.position - view.look_at) / np.linalg.norm(view.position - view.look_at)
    assert abs(direction[0]) > 0.6, direction  # towards the face's normal (x), not along it
