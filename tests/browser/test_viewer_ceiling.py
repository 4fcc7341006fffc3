"""The 3D view opens below an indoor scene's ceiling, and leaves open scenes uncut."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.datasets.lidar import lidar_pair
from app.core.datasets.scenes import raycast_scene
from app.viewer.ceiling import ceiling_cut_height


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_ray_cast_room_is_cut_just_below_its_ceiling(seed: int) -> None:
    pair = raycast_scene(n_points=8000, change="box", random_state=seed)
    points = np.vstack([pair.reference, pair.scan])
    level = ceiling_cut_height(points)
    assert level is not None
    top = points[:, 2].max()
    below = points[:, 2] < level
    # the ceiling (the highest slab) is cut away, most of the scene is kept
    assert level < top - 0.05
    assert below.mean() > 0.5
    assert level > np.quantile(points[:, 2], 0.5)


def test_an_open_scene_is_not_cut() -> None:
    rng = np.random.default_rng(3)
    ground = np.column_stack([rng.uniform(-10, 10, (5000, 2)), rng.normal(0, 0.02, 5000)])
    tree = np.column_stack([rng.normal(2, 0.5, (800, 2)), rng.uniform(0, 6, 800)])
    pole = np.column_stack([rng.normal(-4, 0.05, (300, 2)), rng.uniform(0, 8, 300)])
    assert ceiling_cut_height(np.vstack([ground, tree, pole])) is None
    assert ceiling_cut_height(ground) is None  # flat
    assert ceiling_cut_height(ground[:50]) is None  # too few points


@pytest.mark.parametrize("layout", ["room", "corridor", "warehouse"])
def test_lidar_layouts_are_cut_below_their_ceiling(layout: str) -> None:
    pair = lidar_pair(layout=layout, change="added", angular_step_deg=1.0, random_state=5)
    points = np.vstack([pair.reference, pair.scan])
    level = ceiling_cut_height(points)
    assert level is not None
    assert (points[:, 2] > level).mean() < 0.4  # the ceiling, not half the scene
    assert level < points[:, 2].max() - 0.05
