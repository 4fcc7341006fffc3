"""Stray samples of fused maps (flying pixels, lone returns) are no change (issue 29)."""

from __future__ import annotations

import numpy as np

from app.core.labels import LABEL_CHANGED
from app.core.localise.changes import localise_changes

SPACING = 0.02


def corner_room(rng: np.random.Generator) -> np.ndarray:
    """A 4 x 4 m floor and two 2.5 m walls sampled every 2 cm, 2 mm noise: (n, 3)."""
    grid = np.arange(0.0, 4.0, SPACING)
    floor_x, floor_y = np.meshgrid(grid, grid)
    floor = np.column_stack([floor_x.ravel(), floor_y.ravel(), np.zeros(floor_x.size)])
    along, height = np.meshgrid(grid, np.arange(0.0, 2.5, SPACING))
    back = np.column_stack([along.ravel(), np.full(along.size, 4.0), height.ravel()])
    side = np.column_stack([np.zeros(along.size), along.ravel(), height.ravel()])
    points = np.vstack([floor, back, side])
    return points + rng.normal(0.0, 0.002, points.shape)


def box_faces(low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """The top and four sides of a box standing on the floor, sampled every 2 cm: (b, 3)."""
    xs, ys, zs = (np.arange(low[axis], high[axis], SPACING) for axis in range(3))
    faces = [
        np.column_stack([a.ravel(), b.ravel(), np.full(a.size, high[2])])
        for a, b in [np.meshgrid(xs, ys)]
    ]
    for x in (low[0], high[0]):
        a, b = np.meshgrid(ys, zs)
        faces.append(np.column_stack([np.full(a.size, x), a.ravel(), b.ravel()]))
    for y in (low[1], high[1]):
        a, b = np.meshgrid(xs, zs)
        faces.append(np.column_stack([a.ravel(), np.full(a.size, y), b.ravel()]))
    return np.vstack(faces)


def test_flying_pixels_over_an_unchanged_room_are_no_change() -> None:
    # a depth camera's flying pixels: 80 lone samples in the air over the floor, each far
    # from the others (main called 79 of them one "added" region)
    rng = np.random.default_rng(7)
    reference, scan = corner_room(rng), corner_room(rng)
    flyers = rng.uniform([1.5, 1.5, 0.3], [2.5, 2.5, 1.0], (80, 3))
    result = localise_changes(reference, np.vstack([scan, flyers]))
    assert not (result.scan_label[-len(flyers) :] == LABEL_CHANGED).any()
    assert result.regions == []
    assert result.parameters["scan_stray_samples"] >= 70


def test_an_added_box_among_flying_pixels_is_still_found() -> None:
    rng = np.random.default_rng(8)
    reference, scan = corner_room(rng), corner_room(rng)
    box = box_faces(np.array([1.0, 1.0, 0.0]), np.array([1.4, 1.3, 0.35]))
    flyers = rng.uniform([2.0, 2.0, 0.3], [3.0, 3.0, 1.0], (80, 3))
    result = localise_changes(reference, np.vstack([scan, box, flyers]))
    on_box = result.scan_label[len(scan) : len(scan) + len(box)] == LABEL_CHANGED
    assert on_box.mean() > 0.6  # all but the rows within 10 cm of the floor
    assert not (result.scan_label[-len(flyers) :] == LABEL_CHANGED).any()
    assert [region.kind for region in result.regions] == ["added"]
