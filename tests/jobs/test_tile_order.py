"""The order a tiled job's tiles are handed out in: the largest planned crops first."""

from __future__ import annotations

import numpy as np

from app.core.tiling import TilePlan
from app.jobs.tiles import largest_first


def _plan(crop_points: list[int]) -> TilePlan:
    count = len(crop_points)
    return TilePlan(
        lower=np.zeros((count, 2)),
        upper=np.ones((count, 2)),
        margin=1.0,
        crop_points=np.asarray(crop_points, dtype=np.int64),
        max_crop_points=max(crop_points),
    )


def test_the_largest_planned_crops_come_first_ties_by_index() -> None:
    plan = _plan([10, 40, 25, 40, 5])
    assert largest_first(plan, [0, 1, 2, 3, 4]) == [1, 3, 2, 0, 4]


def test_only_the_tiles_still_to_do_are_ordered() -> None:
    plan = _plan([10, 40, 25, 40, 5])
    assert largest_first(plan, [4, 0, 2]) == [2, 0, 4]
