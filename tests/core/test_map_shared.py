"""The map test on robot maps (issue 29): surfaces both epochs saw in part are no evidence of a
change (a wall beside a box, a desk top over a floor patch), and lines of samples between the
other epoch's lines on a far floor are a coverage difference."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from app.core.datasets.maps import map_pair
from app.core.labels import LABEL_CHANGED
from app.core.localise import localise_changes
from app.core.localise.map_shared import meets_lacking_at_angle
from app.core.pipeline import compare
from tests.helpers.fused_rooms import box_sides, chair_before_wall, plane

ROOM_FLOOR = ([0.0, 0.0, 0.0], [6.0, 4.0, 0.0])


def floor(rng, holes=()):
    """The 6 x 4 m floor without the ``holes`` ((low, high) boxes in x, y)."""
    points = plane(rng, [0, 0, 0], [6, 0, 0], [0, 4, 0])
    return _without(points, [([*low[:2], -1.0], [*high[:2], 1.0]) for low, high in holes])


def _without(points, holes):
    keep = np.ones(points.shape[0], bool)
    for low, high in holes:
        inside = np.ones(points.shape[0], bool)
        for axis in range(3):
            if high[axis] > low[axis]:
                inside &= (points[:, axis] > low[axis]) & (points[:, axis] < high[axis])
        keep &= ~inside
    return points[keep]


def walls(rng, holes=(), spacing=0.03):
    """The room's two walls (y = 0, sampled every ``spacing``, and x = 0) and its ceiling,
    without the ``holes``."""
    return _without(
        np.vstack(
            [
                plane(rng, [0, 0, 0], [6, 0, 0], [0, 0, 2.5], spacing=spacing),
                plane(rng, [0, 0, 0], [0, 4, 0], [0, 0, 2.5]),
                plane(rng, [0, 0, 2.5], [6, 0, 0], [0, 4, 0]),
            ]
        ),
        holes,
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_box_standing_clear_of_a_wall_each_epoch_saw_from_its_own_side_is_unchanged(seed):
    # a guard for the next test: a box 7-9 cm in front of a wall, only the reference's path
    # saw its west face; the wall beside it, seen by both, says nothing either way, and the
    # box's top and north face, which the scan saw end at the face, make it an unseen side
    rng = np.random.default_rng(seed)
    gap = rng.uniform(0.07, 0.09)
    box = ([2.5, gap, 0.0], [2.85, gap + 0.32, 0.5])
    hidden = [([2.5, 0.0, 0.0], [2.85, 0.0, 0.5])]  # the wall behind the box
    # the floor under the box, in the slot behind it and beside its east end (too grazing)
    under = [([2.5, 0.0, 0.0], [3.15, box[1][1], 0.0])]
    # a robot's lidar sees the wall sparsely: its samples around the face's foot reach 0.5 m
    room = [floor(rng, under), walls(rng, hidden, spacing=0.1)]
    reference = np.vstack([*room, box_sides(rng, *box, faces="twen")])
    room = [floor(rng, under), walls(rng, hidden, spacing=0.1)]
    scan = np.vstack([*room, box_sides(rng, *box, faces="ten")])
    localisation = localise_changes(reference, scan)
    assert localisation.parameters["reference_visibility"] == "maps"
    assert np.count_nonzero(localisation.reference_label == LABEL_CHANGED) == 0
    assert localisation.regions == []


def test_a_box_standing_clear_of_a_corridor_wall_is_unchanged():
    # robot corridor 301 of bench.moving_maps: a box 9 cm in front of the corridor's wall,
    # only the reference's path saw its west face.  Both epochs saw the wall past the box's
    # ends and over its top, sampled sparsely: it carried on past the west face's border
    # beside it (in 6-8 of 8 directions, 0.35 of the border), and the face was taken for one
    # whose place the scan saw empty (1 region of 107 points)
    pair = map_pair("robot", layout="corridor", change="none", misaligned=True, random_state=301)
    result = compare(*pair.clouds())
    assert result.regions == []


@pytest.mark.parametrize("seed", [0, 1])
def test_a_box_added_clear_of_a_wall_is_still_added(seed):
    # the guard: the wall beside an added box says nothing either way; the reference saw the
    # floor where the box now stands
    rng = np.random.default_rng(seed)
    box = ([2.5, 0.08, 0.0], [2.8, 0.4, 0.5])
    reference = np.vstack([floor(rng), walls(rng)])
    hidden = [([2.5, 0.0, 0.0], [2.8, 0.0, 0.5])]
    scan = np.vstack(
        [floor(rng, [(box[0], box[1])]), walls(rng, hidden), box_sides(rng, *box, faces="twe")]
    )
    localisation = localise_changes(reference, scan)
    on_box = (scan[:, 2] > 0.12) & (scan[:, 2] < 0.6) & (scan[:, 1] > 0.06)
    on_box &= (scan[:, 0] > 2.45) & (scan[:, 0] < 2.85)
    assert on_box.sum() > 100
    assert np.mean(localisation.scan_label[on_box] == LABEL_CHANGED) >= 0.9


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_floor_patch_under_a_desk_top_the_other_epoch_saw_more_of_is_unchanged(seed):
    # robot office 303 of bench.moving_maps: the scan's lidar saw the floor under a desk that
    # the reference's never saw, and the reference saw the part of the desk's top over it that
    # the scan's did not.  The reference's desk top, surface the scan lacks on the floor
    # patch's normal lines, was taken for the scan having seen through the patch's place (a
    # region); a level part is seen from above, and surface over it only hid it.  The guard:
    # the reference's piece of desk top over the patch is the geometry of a piece of desk top
    # removed, the floor under it seen from above by the scan; it stays removed (no origins
    # tell the two apart; on robot 303 it was no region either way)
    rng = np.random.default_rng(seed)
    desk = ([2.0, 1.0, 0.0], [3.0, 2.0, 0.0])
    patch = ([2.0, 1.2, -1.0], [2.45, 1.8, 1.0])
    top = plane(rng, [2.0, 1.0, 0.75], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], spacing=0.02)
    reference = np.vstack([floor(rng, [desk]), walls(rng), top])
    scan_floor = np.vstack([floor(rng, [desk]), _patch(rng)])
    scan = np.vstack([scan_floor, walls(rng), _without(top, [patch])])
    localisation = localise_changes(reference, scan)
    assert localisation.parameters["scan_visibility"] == "maps"
    assert np.count_nonzero(localisation.scan_label == LABEL_CHANGED) == 0
    assert all(region.kind == "removed" for region in localisation.regions)
    # the piece's points farther than the change threshold from the scan's desk top
    piece = (np.abs(reference[:, 2] - 0.75) < 0.01) & (reference[:, 0] > 2.02)
    piece &= (reference[:, 0] < 2.33) & (reference[:, 1] > 1.32) & (reference[:, 1] < 1.68)
    assert np.mean(localisation.reference_label[piece] == LABEL_CHANGED) >= 0.9


def _patch(rng):
    """The floor under the desk that only the scan saw."""
    return plane(rng, [2.0, 1.2, 0.0], [0.45, 0.0, 0.0], [0.0, 0.6, 0.0])


def test_a_wall_section_pushed_out_is_still_seen_through():
    # the guard (the paper's corridor, as test_localise's): the scan's wall section 0.5 m in
    # front of the reference's is surface of the scan alone, carrying on into nothing both
    # epochs saw, so the reference's wall patch behind it stays removed
    rng = np.random.default_rng(4)
    section = ([2.0, 0.0, 0.5], [3.0, 0.0, 1.5])
    reference = np.vstack([floor(rng), walls(rng)])
    moved = plane(rng, [2.0, 0.5, 0.5], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    scan = np.vstack([floor(rng), walls(rng, [section]), moved])
    localisation = localise_changes(reference, scan)
    patch = (np.abs(reference[:, 1]) < 0.01) & (reference[:, 2] > 0.65) & (reference[:, 2] < 1.35)
    patch &= (reference[:, 0] > 2.15) & (reference[:, 0] < 2.85)
    assert patch.sum() > 100
    assert np.mean(localisation.reference_label[patch] == LABEL_CHANGED) >= 0.9


@pytest.mark.parametrize(("seed", "gap"), [(0, 0.10), (1, 0.10), (2, 0.12)])
def test_a_wall_patch_a_removed_chairs_back_hid_just_before_it_is_unchanged(seed, gap):
    # robot warehouse 2804: the reference's chair back stood a change threshold before the
    # wall, which the scan (the chair removed) saw whole.  The scan's wall patch carries on
    # into the reference's wall all round; the back on its normal line hid it from the
    # reference (no sensor saw the wall's place empty through it), while the back itself is
    # still removed
    reference, scan, back, hidden = chair_before_wall(np.random.default_rng(seed), gap=gap)
    localisation = localise_changes(reference, scan)
    assert localisation.parameters["change_threshold"] == pytest.approx(0.1)
    assert hidden.sum() > 150
    assert np.mean(localisation.scan_label[hidden] == LABEL_CHANGED) <= 0.05
    assert np.mean(localisation.reference_label[back] == LABEL_CHANGED) >= 0.6


def floor_lines(rng, xs, *, step=0.05):
    """Single lidar lines across the floor at x = ``xs``, every ``step`` metres (two sweeps'
    returns each, a few millimetres apart)."""
    y = np.arange(0.1, 3.9, step)
    lines = [
        np.column_stack([x + 0.008 * row + rng.normal(0.0, 0.003, y.size), y, np.zeros(y.size)])
        for x in xs
        for row in range(2)
    ]
    return np.vstack(lines)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_single_scan_lines_metres_apart_each_epoch_in_its_own_place_are_not_changed(seed):
    # robot corridor 801 of bench.moving_maps: a 16-ring lidar sees the corridor's ceiling
    # only from 6.5 m on, in ring arcs a metre apart; each epoch's arcs lay 0.6-3 m from the
    # other's, beyond the 0.5 m that the gaps between scan lines are looked for in (3 regions)
    rng = np.random.default_rng(seed)
    lines = ([2.6, 0.0, 0.0], [5.0, 4.0, 0.0])
    shift = rng.uniform(0.55, 0.65)
    reference = np.vstack([floor(rng, [lines]), walls(rng), floor_lines(rng, [3.2, 4.4])])
    scan = np.vstack([floor(rng, [lines]), walls(rng), floor_lines(rng, [3.2 + shift])])
    localisation = localise_changes(reference, scan)
    for cloud, label in (
        (reference, localisation.reference_label),
        (scan, localisation.scan_label),
    ):
        between = (cloud[:, 0] > lines[0][0] + 0.05) & (cloud[:, 0] < lines[1][0] - 0.05)
        assert np.count_nonzero(label[between] == LABEL_CHANGED) == 0
    assert localisation.regions == []


def test_a_strip_of_a_rack_end_next_to_its_corner_is_not_changed():
    # robot warehouse 804 of bench.moving_maps: each path saw a rack's end face in lidar
    # columns, the reference's two 9-26 cm from the rack's corner, the scan's 0.4 m and more
    # from it.  The strip lay between the scan's columns on the face and the corner, where the
    # scan's side of the rack ends; too few of its border points (4) met that side for an
    # unseen side, and its half-plane towards the corner was empty: a false region of 28
    # points beside the removed box (IoU 0.663)
    pair = map_pair("robot", layout="warehouse", change="removed", random_state=804)
    reference, scan = pair.clouds()
    localisation = localise_changes(reference.points, scan.points)
    label = localisation.reference_label
    false = (label == LABEL_CHANGED) & ~pair.reference_changed & pair.reference_scored
    assert np.count_nonzero(false) == 0
    box = pair.reference_changed & pair.reference_scored
    assert np.mean(label[box] == LABEL_CHANGED) >= 0.9


def test_a_backrest_turned_in_place_is_no_strip_of_a_face_both_saw():
    # the guard of the edge strips (robot warehouse 604 of bench.moving_maps): a chair turned a
    # quarter in place, its new backrest seen by the scan from afar (16 points): on the plane
    # of the seat's side, which the reference saw, with 3 border points where the reference's
    # surfaces end at it, as a strip of a face both saw.  It meets the old backrest, surface
    # the scan lacks, at a right angle next to it: the s17 edge-strip rule made it an unseen
    # side (none of its points changed; 14 of 16 are with the turned-face test)
    pair = map_pair(
        "robot", layout="warehouse", change="rotated", misaligned=True, random_state=604
    )
    reference, scan = pair.clouds()
    localisation = localise_changes(reference.points, scan.points)
    new_backrest = pair.scan_changed & pair.scan_scored
    assert np.count_nonzero(new_backrest) > 0
    assert np.mean(localisation.scan_label[new_backrest] == LABEL_CHANGED) >= 0.75


def _cloud(points, normals):
    """The two attributes of a side that the meeting probe reads (points and their normals)."""
    return SimpleNamespace(points=points, geometry=SimpleNamespace(normal=normals))


def _sheet(rng, origin, first, second, spacing):
    points = plane(rng, origin, first, second, spacing=spacing)
    normal = np.cross(first, second) / np.linalg.norm(np.cross(first, second))
    return points, np.broadcast_to(normal, points.shape).astype(np.float32)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_only_a_face_meeting_surface_this_epoch_lacks_at_an_angle_is_turned_in_place(seed):
    # a sparse upright face (a new backrest seen from afar, on the plane y = 2) against the
    # other epoch's upright surfaces next to it: its old face round the corner, lacking in this
    # epoch, meets it at a right angle (turned in place); the other epoch's own columns on the
    # same plane (a strip of a face both saw), the same corner face 0.5 m off, or matched by
    # this epoch, do not
    rng = np.random.default_rng(seed)
    face, _ = _sheet(rng, [2.5, 2.0, 0.45], [0.3, 0, 0], [0, 0, 0.4], spacing=0.09)
    labels = np.zeros(face.shape[0], dtype=np.int64)
    check = np.array([True])
    gap = rng.uniform(0.04, 0.08)
    corner, corner_normal = _sheet(rng, [2.8 + gap, 1.5, 0.45], [0, 0.45, 0], [0, 0, 0.5], 0.03)
    columns, columns_normal = _sheet(rng, [2.95, 2.0, 0.45], [0.3, 0, 0], [0, 0, 0.4], 0.03)
    far, far_normal = _sheet(rng, [3.3, 1.5, 0.45], [0, 0.45, 0], [0, 0, 0.5], 0.03)
    reach = 0.2
    lacking = np.ones(corner.shape[0], dtype=bool)
    met = meets_lacking_at_angle(face, labels, check, _cloud(corner, corner_normal), lacking, reach)
    assert met.tolist() == [True]
    for other, normal in ((columns, columns_normal), (far, far_normal)):
        lacking = np.ones(other.shape[0], dtype=bool)
        met = meets_lacking_at_angle(face, labels, check, _cloud(other, normal), lacking, reach)
        assert met.tolist() == [False]
    matched = np.zeros(corner.shape[0], dtype=bool)
    met = meets_lacking_at_angle(face, labels, check, _cloud(corner, corner_normal), matched, reach)
    assert met.tolist() == [False]


def ceiling_arcs(rng, offsets, *, height=2.5, step=0.09):
    """Lidar ring arcs on a ceiling at ``height``, across the room's corner at x = y = 0: the
    lines x + y = d for each ``offsets`` d, a sample every ``step`` metres along them."""
    arcs = []
    for offset in offsets:
        x = np.arange(0.5 * step, offset, step)
        x = x + rng.normal(0.0, 0.003, x.size)
        arcs.append(np.column_stack([x, offset - x, height + rng.normal(0.0, 0.005, x.size)]))
    return np.vstack(arcs)


def bare_walls(rng, height=2.5):
    """The room's two walls (y = 0 and x = 0) up to the ceiling, whose surface is not sampled."""
    return np.vstack(
        [
            plane(rng, [0, 0, 0], [6, 0, 0], [0, 0, height], spacing=0.03),
            plane(rng, [0, 0, 0], [0, 4, 0], [0, 0, height]),
        ]
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ceiling_arcs_each_epoch_saw_in_its_own_place_by_a_corner_are_not_changed(seed):
    # robot office 903 of bench.moving_maps (unchanged): a 16-ring lidar sees the ceiling
    # 1.9 m up only far from its path, in ring arcs; in a corner the reference's arcs lay
    # nearest the corner, the scan's two 0.8-1.2 m out, side by side.  Nothing of the
    # reference's lies under or over them within reach (the floor is 2.5 m down), but its
    # ceiling arcs lie on their plane nearby: a coverage difference (main: 2 regions)
    rng = np.random.default_rng(seed)
    out = rng.uniform(1.2, 1.4)
    reference = np.vstack([floor(rng), bare_walls(rng), ceiling_arcs(rng, [0.35, 0.52, 0.69])])
    scan = np.vstack([floor(rng), bare_walls(rng), ceiling_arcs(rng, [out, out + 0.17])])
    localisation = localise_changes(reference, scan)
    high = scan[:, 2] > 2.4
    assert np.count_nonzero(localisation.scan_label[high] == LABEL_CHANGED) == 0
    assert localisation.regions == []
