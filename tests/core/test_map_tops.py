"""The map test's level tops held up in both epochs (issue 29, :mod:`app.core.localise.map_tops`):
a desk top one path never saw, its legs and the floor under it seen by both, is a coverage
difference; a removed table (its legs gone too) and a box removed from a desk top stay
changes."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.labels import LABEL_CHANGED
from app.core.localise import localise_changes
from app.core.localise.distance import Side
from app.core.localise.map_tops import held_tops
from app.core.localise.surface import local_geometry
from tests.helpers.fused_rooms import box_sides, fused_room, plane

DESK_HEIGHT = 0.74
DESK = ((2.0, 1.5), (3.4, 2.2))
"""An open desk's top corners (x, y), in the middle of the room."""


def noisy(rng, points, noise=0.008):
    """``points`` with a robot map's noise (8 mm)."""
    return points + rng.normal(0.0, noise, points.shape)


def desk_top(rng):
    (x0, y0), (x1, y1) = DESK
    return plane(rng, [x0, y0, DESK_HEIGHT], [x1 - x0, 0, 0], [0, y1 - y0, 0])


def legs(rng):
    """The desk's four 5 cm legs, their sides only."""
    (x0, y0), (x1, y1) = DESK
    return np.vstack(
        [
            box_sides(rng, [x, y, 0.0], [x + 0.05, y + 0.05, DESK_HEIGHT - 0.03], faces="nsew")
            for x in (x0, x1 - 0.05)
            for y in (y0, y1 - 0.05)
        ]
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_desk_top_the_other_path_never_saw_is_no_change(seed):
    # robot office 2002 of bench.moving_maps (held-out seeds): the scan passed the desk with its
    # lidar level with the top and saw its legs and the floor under it, never its top; the
    # floor under the open desk made the top a removed table's (384 false points)
    rng = np.random.default_rng(seed)
    top = desk_top(rng)
    reference = noisy(rng, np.vstack([fused_room(rng), legs(rng), top]))
    scan = noisy(rng, np.vstack([fused_room(rng), legs(rng)]))
    localisation = localise_changes(reference, scan)
    assert localisation.parameters["reference_visibility"] == "maps"
    label = localisation.reference_label[-top.shape[0] :]
    assert np.mean(label == LABEL_CHANGED) <= 0.05


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_removed_desk_keeps_its_top_changed(seed):
    # the same desk gone with its legs: nothing of the scan's stands under the top
    rng = np.random.default_rng(seed)
    top = desk_top(rng)
    reference = noisy(rng, np.vstack([fused_room(rng), legs(rng), top]))
    scan = noisy(rng, fused_room(rng))
    localisation = localise_changes(reference, scan)
    label = localisation.reference_label[-top.shape[0] :]
    assert np.mean(label == LABEL_CHANGED) >= 0.6


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_box_removed_from_a_desk_keeps_its_top_changed(seed):
    # the desk top is the first level surface under the box's top: the legs under it hold the
    # desk, not the box
    rng = np.random.default_rng(seed)
    low, high = (2.3, 1.6, DESK_HEIGHT), (2.8, 2.05, DESK_HEIGHT + 0.4)
    box = box_sides(rng, low, high)
    box_top = box[: plane(rng, [0, 0, 0], [0.5, 0, 0], [0, 0.45, 0]).shape[0]]
    desk = np.vstack([legs(rng), desk_top(rng)])
    reference = noisy(rng, np.vstack([fused_room(rng), desk, box]))
    scan = noisy(rng, np.vstack([fused_room(rng), desk]))
    localisation = localise_changes(reference, scan)
    label = localisation.reference_label[-box.shape[0] :][: box_top.shape[0]]
    assert np.mean(label == LABEL_CHANGED) >= 0.6


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_chair_removed_from_a_wall_seen_below_its_seat_only_keeps_its_seat_changed(seed):
    # RGB-D room 800 of bench.moving_maps: the scan saw the wall beside a removed chair only
    # below the seat's height (over it, the wall was out of its frames), so a strip of wall both
    # epochs share stood under the seat with nothing over it, 0.38 m long: it held the seat up
    # as two legs would and hid the whole removed chair (98 -> 0 %).  A wall is no post.
    rng = np.random.default_rng(seed)
    seat_low, seat_high = (0.06, 1.5, 0.42), (0.5, 1.95, 0.45)
    seat = box_sides(rng, seat_low, seat_high, faces="t", spacing=0.015)
    chair_legs = np.vstack(
        [
            box_sides(rng, [x, y, 0.0], [x + 0.03, y + 0.03, 0.42], faces="nsew", spacing=0.015)
            for x in (0.08, 0.45)
            for y in (1.52, 1.9)
        ]
    )
    room = fused_room(rng)
    beside_chair = (room[:, 0] < 0.01) & (room[:, 1] > 1.3) & (room[:, 1] < 2.15)
    unseen_over_seat = beside_chair & (room[:, 2] > 0.38)
    reference = noisy(rng, np.vstack([fused_room(rng), chair_legs, seat]))
    scan = noisy(rng, room[~unseen_over_seat])
    localisation = localise_changes(reference, scan)
    label = localisation.reference_label[-seat.shape[0] :]
    assert np.mean(label == LABEL_CHANGED) >= 0.6


def _front_rim_strip(rng, x_from, x_to):
    """The desk's front edge (y = its low y) from ``x_from`` to ``x_to``: a strip 3 cm deep
    at the top's height, as a path at the lidar's height samples it."""
    (_, y0), _ = DESK
    strip = plane(rng, [x_from, y0, DESK_HEIGHT], [x_to - x_from, 0, 0], [0, 0.03, 0], 0.02)
    return noisy(rng, strip)


def _held(rng, part, with_legs):
    """:func:`held_tops` of one part (shape (p, 3)) against a floor and, ``with_legs``, the
    desk's legs seen by both epochs."""
    other = noisy(rng, np.vstack([fused_room(rng)] + ([legs(rng)] if with_legs else [])))
    nowhere = np.zeros(other.shape[0])
    side = Side("scan", "added", other, None, local_geometry(other, 10), nowhere, nowhere)
    return held_tops(
        part,
        np.zeros(part.shape[0], dtype=np.int64),
        np.array([True]),
        other=side,
        other_unmatched=np.zeros(other.shape[0], dtype=bool),
        change_threshold=0.1,
    )[0]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_rim_strip_between_legs_is_held_up_by_them(seed):
    # robot office 2003 of bench.moving_maps (held-out seeds, unchanged): the reference saw a
    # desk's front rim at its lidar's height, the scan its legs and the rest of the desk only.
    # The strip's points next to the legs are within the change threshold of the legs' tops:
    # its candidates end 0.26-0.4 m short of them, out of reach under the part (1 region of 39
    # points, a wrong decision)
    rng = np.random.default_rng(seed)
    (x0, _), (x1, _) = DESK
    assert _held(rng, _front_rim_strip(rng, x0 + 0.3, x1 - 0.3), with_legs=True)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_rim_strip_of_a_removed_desk_is_held_by_nothing(seed):
    # the same strip with the desk gone, legs and all: nothing holds it up
    rng = np.random.default_rng(seed)
    (x0, _), (x1, _) = DESK
    assert not _held(rng, _front_rim_strip(rng, x0 + 0.3, x1 - 0.3), with_legs=False)


@pytest.mark.parametrize("seed", [0, 1])
def test_a_top_patch_is_not_reached_past_its_ends(seed):
    # a patch of a top, no line: the legs 0.3 m beyond its ends hold it up only when they
    # stand under it
    rng = np.random.default_rng(seed)
    (x0, y0), _ = DESK
    patch = noisy(rng, plane(rng, [x0 + 0.3, y0, DESK_HEIGHT], [0.8, 0, 0], [0, 0.7, 0], 0.02))
    assert not _held(rng, patch, with_legs=True)
