"""A turned box's faces: an L of two turned faces meets the old box's side (issue 29).

Robot warehouse 2104 of ``bench.moving_maps``: a box turned a quarter in place.  The new box's
long side stands out past the old box's side; its far end, an L of the long side and the end
face under ``min_region_points``, meets the old box's region along the long side only, while
the plane fitted to the L is the larger end face's, parallel to the old side: each meeting
point's angle is its own normal's (``turned_faces._meets_at_angle``)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from app.core.labels import LABEL_CHANGED
from app.core.localise.regions import find_regions
from app.core.localise.turned_faces import changed_points, turned_faces
from app.core.localise.visibility import Labelled


def _grid(rng, xs, ys, zs, noise=0.003):
    """Points on the grid of ``xs`` x ``ys`` x ``zs`` (one of them a single value), jittered."""
    grid = np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), axis=-1).reshape(-1, 3)
    return grid + rng.normal(0.0, noise, grid.shape)


def _changed(points, normals, name, kind, spacing):
    """One cloud's changed points (all of ``points``) as the map test judged them."""
    count = points.shape[0]
    geometry = SimpleNamespace(normal=normals.astype(np.float32), spacing=np.full(count, spacing))
    side = SimpleNamespace(name=name, region_kind=kind, points=points, geometry=geometry)
    labelled = Labelled(
        label=np.full(count, LABEL_CHANGED, dtype=np.int8),
        evidence=np.ones(count, dtype=np.int8),
        confidence=np.ones(count, dtype=np.float32),
        report={f"{name}_visibility": "maps"},
    )
    return changed_points(side, labelled, np.full(count, 0.2))  # type: ignore[arg-type]


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize(("side_y", "kept"), [(-0.05, True), (-0.25, False)])
def test_an_l_of_two_turned_faces_meets_the_old_side_along_one(seed, side_y, kept):
    # the new box's end (scan): its side x = 0.3 from ``side_y`` to -0.19 (normal x) and its
    # end face y = -0.22 (normal y, the larger: the plane fitted to the L is about its);
    # the old box's side (reference region, plane y = 0, normal y) 5-19 cm from the new
    # side, 22 cm from the end face.  The points that meet the old side are the new side's,
    # at a right angle to it.  With the side starting 25 cm off (``side_y`` -0.25: none of
    # it within two change thresholds), nothing meets the old side
    rng = np.random.default_rng(seed)
    spacing = 0.05
    side = _grid(rng, [0.3], np.arange(side_y, -0.19, -spacing), np.arange(0.0, 0.5, spacing))
    end = _grid(rng, np.arange(0.0, 0.3, spacing), [-0.22], np.arange(0.0, 0.5, spacing))
    new_points = np.vstack([side, end])
    normals = np.vstack(
        [np.tile([1.0, 0.0, 0.0], (side.shape[0], 1)), np.tile([0.0, 1.0, 0.0], (end.shape[0], 1))]
    )
    new = _changed(new_points, normals, "scan", "added", spacing)
    old_points = _grid(rng, np.arange(-0.1, 0.45, spacing), [0.0], np.arange(0.0, 0.5, spacing))
    old = _changed(
        old_points,
        np.tile([0.0, 1.0, 0.0], (old_points.shape[0], 1)),
        "reference",
        "removed",
        spacing,
    )
    regions, _ = find_regions(
        old.side.points,
        kind="removed",
        changed=old.changed,
        spacing=old.side.geometry.spacing,
        distance=old.distance,
        cluster_factor=2.5,
        min_region_points=new_points.shape[0] + 1,
    )
    assert len(regions) == 1

    found = turned_faces(
        (old, new),
        regions,
        cluster_factor=2.5,
        min_region_points=new_points.shape[0] + 1,
        change_threshold=0.1,
    )

    assert [region.kind for region in found] == (["added"] if kept else [])
