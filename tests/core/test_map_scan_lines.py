"""The map test on sparse robot maps (issue 29): single scan lines on a floor far from both paths,
each epoch's in its own place, are a coverage difference."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.labels import LABEL_CHANGED
from app.core.localise import localise_changes
from tests.helpers.fused_rooms import box_sides, fused_room, plane

FAR_END = ([4.2, 0.0, 0.0], [6.0, 4.0, 0.0])
"""The room's far end: its floor sampled by single scan lines only, up to its end wall."""


def far_room(rng, lines):
    """A room whose floor beyond x = 4.2 m was seen in single lines only, with its end wall."""
    return np.vstack(
        [fused_room(rng, floor_hole=FAR_END), plane(rng, [6, 0, 0], [0, 4, 0], [0, 0, 2.5]), lines]
    )


def floor_lines(rng, xs, *, step=0.06, rows=2):
    """Single lidar lines across the floor at x = ``xs`` (two sweeps' returns each, a few
    millimetres apart, bending a little as a ring's arc does), every ``step`` metres."""
    lines = []
    for x in xs:
        y = np.arange(0.1, 3.9, step)
        for row in range(rows):
            bend = 0.03 * ((y - 2.0) / 2.0) ** 2
            points = np.column_stack(
                [x + bend + 0.008 * row + rng.normal(0.0, 0.003, y.size), y, np.zeros(y.size)]
            )
            points[:, 2] += rng.normal(0.0, 0.003, y.size)
            lines.append(points)
    return np.vstack(lines)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_single_scan_lines_on_a_far_floor_each_epoch_in_its_own_place_are_not_changed(seed):
    # robot corridor 501 of bench.moving_maps: at the corridor's far end each epoch saw the
    # floor in single ring arcs, the reference's 0.25-0.35 m from the scan's.  Each line lies
    # farther than the change distance from every point of the other epoch, yet on the floor
    # the other epoch's lines span, between them; a line has no normal of its own, so it
    # "continued" into nothing and was called changed
    rng = np.random.default_rng(seed)
    offset = rng.uniform(0.25, 0.35)
    reference = far_room(rng, floor_lines(rng, [4.3, 4.9, 5.5]))
    scan = far_room(rng, floor_lines(rng, np.array([4.3, 4.9, 5.5]) + offset))
    localisation = localise_changes(reference, scan)
    assert localisation.parameters["reference_visibility"] == "maps"
    for cloud, label in (
        (reference, localisation.reference_label),
        (scan, localisation.scan_label),
    ):
        far = cloud[:, 0] > FAR_END[0][0] + 0.05
        assert np.count_nonzero(label[far] == LABEL_CHANGED) == 0
    assert localisation.regions == []


def test_a_removed_box_whose_top_was_seen_in_single_scan_lines_is_still_removed():
    # the guard: lines on a box top lie on no plane of the other epoch (its floor is 0.6 m
    # down), so they are no gap between the other epoch's samples
    rng = np.random.default_rng(3)
    box = ([4.6, 1.2, 0.0], [5.6, 2.6, 0.6])
    top = floor_lines(rng, [4.7, 5.0, 5.3])
    top = top[(top[:, 1] > box[0][1]) & (top[:, 1] < box[1][1])] + [0.0, 0.0, 0.6]
    reference = np.vstack(
        [fused_room(rng, floor_hole=box), box_sides(rng, *box, faces="nsw", spacing=0.03), top]
    )
    scan = fused_room(rng)
    localisation = localise_changes(reference, scan)
    assert top.shape[0] > 100
    on_top = localisation.reference_label[-top.shape[0] :]
    assert np.mean(on_top == LABEL_CHANGED) >= 0.9
