"""The map test on sparse maps (issue 29): the foot of an upright face, within the change
threshold above a support the other epoch sampled only round it, is no change of its own."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.labels import LABEL_CHANGED
from app.core.localise import localise_changes
from app.core.localise.map_supports import resting_on_support
from app.core.localise.surface import local_geometry
from tests.helpers.fused_rooms import box_sides, plane

BOX = ([2.5, 1.5, 0.0], [3.0, 2.0, 0.6])


def _room(rng, hole):
    """A 6 x 4 m floor without ``hole`` ((low, high) in x, y), a wall at y = 0 and one at
    x = 0."""
    floor = plane(rng, [0, 0, 0], [6, 0, 0], [0, 4, 0])
    (x0, y0), (x1, y1) = hole
    inside = (floor[:, 0] > x0) & (floor[:, 0] < x1) & (floor[:, 1] > y0) & (floor[:, 1] < y1)
    return np.vstack(
        [
            floor[~inside],
            plane(rng, [0, 0, 0], [6, 0, 0], [0, 0, 2.5]),
            plane(rng, [0, 0, 0], [0, 4, 0], [0, 0, 2.5]),
        ]
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_an_added_box_keeps_its_change_but_not_its_foot_over_a_floor_seen_round_it(seed):
    # the reference's path saw the floor only from 0.25-0.35 m round the box's footprint on
    # (a sparse map's gap); the added box's sides stand on that floor, and their lowest
    # centimetres lie within the change threshold of it in the reference's world, although
    # farther than it from every reference sample
    rng = np.random.default_rng(seed)
    margin = rng.uniform(0.25, 0.35)
    (x0, y0, _), (x1, y1, _) = BOX
    reference = _room(rng, ((x0 - margin, y0 - margin), (x1 + margin, y1 + margin)))
    box = box_sides(rng, *BOX, faces="tnsew")
    scan = np.vstack([_room(rng, ((x0, y0), (x1, y1))), box])
    localisation = localise_changes(reference, scan)
    assert localisation.parameters["scan_visibility"] == "maps"
    label = localisation.scan_label[-box.shape[0] :]
    side = np.abs(box[:, 2] - BOX[1][2]) > 0.01
    foot = side & (box[:, 2] < 0.08)
    body = box[:, 2] > 0.15
    assert np.mean(label[body] == LABEL_CHANGED) >= 0.95
    assert np.count_nonzero(label[foot] == LABEL_CHANGED) == 0


def test_only_upright_candidates_over_a_level_support_rest_on_it():
    rng = np.random.default_rng(0)
    floor = plane(rng, [0, 0, 0], [2, 0, 0], [0, 2, 0])
    other = local_geometry(floor, 10)
    points = np.array(
        [
            [1.0, 1.0, 0.06],  # a side's foot over the floor
            [1.0, 1.0, 0.14],  # higher than the change threshold
            [1.0, 1.0, 0.06],  # level: left to the sampling-gap probe
            [5.0, 5.0, 0.06],  # no floor near
        ]
    )
    normal = np.array([[1.0, 0, 0], [1.0, 0, 0], [0, 0, 1.0], [1.0, 0, 0]])
    bottom = np.full(4, 0.03)
    found = resting_on_support(points, normal, bottom, other, tolerance=0.02, change_threshold=0.1)
    assert found.tolist() == [True, False, False, False]
    # a face whose part reaches lower than the level surface passes it by
    found = resting_on_support(
        points, normal, np.full(4, -0.3), other, tolerance=0.02, change_threshold=0.1
    )
    assert not found.any()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_an_added_board_passing_a_low_box_beside_it_stays_changed_at_the_box_tops_height(seed):
    # RGB-D room 1002's moved board: its middle band lay just over the top of a shelf 0.35 m
    # beside it; that top is no support of the board, which reaches down past it
    rng = np.random.default_rng(seed)
    top = rng.uniform(0.35, 0.45)
    low_box = ([2.0, 1.5, 0.0], [2.4, 2.1, top])
    reference = np.vstack([_room(rng, ((0, 0), (0, 0))), box_sides(rng, *low_box)])
    board = plane(rng, [2.75, 1.5, 0.0], [0, 0.6, 0], [0, 0, 0.9])
    scan = np.vstack([_room(rng, ((0, 0), (0, 0))), box_sides(rng, *low_box), board])
    localisation = localise_changes(reference, scan)
    label = localisation.scan_label[-board.shape[0] :]
    band = (board[:, 2] > top + 0.01) & (board[:, 2] < top + 0.09)
    assert np.mean(label[band] == LABEL_CHANGED) >= 0.95
