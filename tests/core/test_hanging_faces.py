"""The map test on fused maps (issue 29): a face of this epoch within the change distance of a
side of a closed body that the other epoch never saw (it hangs under that body's top edge) is
no change; beside an open table (the floor seen under its top) it stays one
(:mod:`app.core.localise.hanging_faces`)."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.labels import LABEL_CHANGED
from app.core.localise import localise_changes
from tests.helpers.fused_rooms import box_sides, fused_room, plane

OLD = ((2.0, 1.0, 0.0), (2.55, 1.33, 0.69))
"""The reference's box (low and high corners): 0.55 x 0.33 m, 0.69 m high."""
NEW = ((2.11, 0.89, 0.0), (2.44, 1.44, 0.69))
"""The scan's box: the same box turned a quarter in place (robot warehouse 1104)."""


def noisy(rng, points, noise=0.008):
    """``points`` with a robot map's noise (8 mm)."""
    return points + rng.normal(0.0, noise, points.shape)


def past_the_unseen_side(points):
    """Which ``points`` of the new box's long faces stand 1-9 cm north of the old box's north
    side, under its top by more than the change distance: within 10 cm of that side."""
    return (
        (points[:, 1] > OLD[1][1] + 0.01)
        & (points[:, 1] < OLD[1][1] + 0.09)
        & (points[:, 2] < OLD[1][2] - 0.15)
        & (points[:, 2] > 0.12)
    )


def turned_box(rng):
    """The new box as the scan's path saw it: its top, its long faces and its north end."""
    return box_sides(rng, NEW[0], NEW[1], faces="twen")


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_face_by_a_closed_body_s_unseen_side_is_no_change(seed):
    # the reference's path saw the old box's top, south side and ends, never its north side;
    # the new box's long faces carry on 11 cm past it, nothing of the reference within 10 cm
    # of them there but that unseen side, which hangs under the old top's north edge
    rng = np.random.default_rng(seed)
    old = box_sides(rng, OLD[0], OLD[1], faces="tswe")
    reference = noisy(rng, np.vstack([fused_room(rng, box=None, floor_hole=OLD[:2]), old]))
    new = turned_box(rng)
    scan = noisy(rng, np.vstack([fused_room(rng, floor_hole=NEW[:2]), new]))
    localisation = localise_changes(reference, scan)
    assert localisation.parameters["scan_visibility"] == "maps"
    new_points = scan[-new.shape[0] :]
    label = localisation.scan_label[-new.shape[0] :]
    band = past_the_unseen_side(new_points) & (
        (np.abs(new_points[:, 0] - NEW[0][0]) < 0.02)
        | (np.abs(new_points[:, 0] - NEW[1][0]) < 0.02)
    )
    assert band.sum() > 20
    assert np.mean(label[band] == LABEL_CHANGED) <= 0.1
    # the new box's north end, 11 cm past the old side, stays a change
    end = (np.abs(new_points[:, 1] - NEW[1][1]) < 0.01) & (new_points[:, 2] > 0.15)
    assert np.mean(label[end] == LABEL_CHANGED) >= 0.6


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_face_by_an_open_table_stays_a_change(seed):
    # the reference's table (its top on a pedestal, the floor seen under it) has no side:
    # the new box's long faces past its edge are more than 10 cm from every surface of it
    rng = np.random.default_rng(seed)
    (x0, y0, _), (x1, y1, height) = OLD
    top = plane(rng, [x0, y0, height], [x1 - x0, 0, 0], [0, y1 - y0, 0])
    middle = np.array([(x0 + x1) / 2, (y0 + y1) / 2])
    pedestal = box_sides(rng, [*middle - 0.05, 0.0], [*middle + 0.05, height - 0.02], faces="nsew")
    reference = noisy(rng, np.vstack([fused_room(rng), pedestal, top]))
    new = turned_box(rng)
    scan = noisy(rng, np.vstack([fused_room(rng, floor_hole=NEW[:2]), new]))
    localisation = localise_changes(reference, scan)
    new_points = scan[-new.shape[0] :]
    label = localisation.scan_label[-new.shape[0] :]
    band = past_the_unseen_side(new_points)
    assert band.sum() > 20
    assert np.mean(label[band] == LABEL_CHANGED) >= 0.6
