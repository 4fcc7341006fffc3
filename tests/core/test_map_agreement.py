"""The two epochs' map tests agree (issue 29): a part is an unseen face of an object standing in
both epochs only if the other epoch's surfaces meeting it are no change of the other epoch's.
With them, two rules of the map test's surface parts: a part is upright or level, never both,
and upright surfaces wholly under an upright part's every adjoining border point hold it up
(no face of its object)."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.datasets.maps import map_pair
from app.core.labels import LABEL_CHANGED
from app.core.localise import localise_changes
from app.core.localise.map_parts import surface_parts
from tests.helpers.fused_rooms import box_sides, fused_room

SEAT = ([2.5, 1.5, 0.0], [3.0, 2.0, 0.45])
OLD_BACK = ([2.96, 1.5, 0.45], [3.0, 2.0, 0.95])
NEW_BACK = ([2.5, 1.96, 0.45], [3.0, 2.0, 0.95])


@pytest.mark.parametrize("seed", [1, 2])
def test_an_old_backrest_meeting_the_turned_one_at_their_corner_is_changed(seed):
    # RGB-D room 803 of bench.moving_maps: a chair turned a quarter in place.  The reference
    # saw its backrest's back, its top and the chair's back below it; the scan saw only the top
    # 12 cm of the new backrest and nothing around the chair.  The old backrest meets the new
    # one at the corner they share and ends there, as a box's side meets another side that
    # only the other path faced: an unseen face (0-3 % changed on seeds 1-4).  But the new
    # backrest, past the change threshold from the old one, is a change of the scan's: the
    # two are no faces of one object standing in both epochs.
    rng = np.random.default_rng(seed)
    reference = np.vstack(
        [
            fused_room(rng, floor_hole=SEAT),
            box_sides(rng, *SEAT, faces="e", spacing=0.01),
            box_sides(rng, *OLD_BACK, faces="te", spacing=0.01),
        ]
    )
    new_back = box_sides(rng, *NEW_BACK, faces="ts", spacing=0.01)
    around = ([2.2, 1.2, 0.0], [3.3, 2.3, 0.0])
    scan = np.vstack([fused_room(rng, floor_hole=around), new_back[new_back[:, 2] > 0.83]])
    localisation = localise_changes(reference, scan)
    assert localisation.parameters["reference_visibility"] == "maps"
    old = (np.abs(reference[:, 0] - 3.0) < 0.01) & (reference[:, 1] < 1.85)
    old &= reference[:, 2] > 0.6
    assert np.mean(localisation.reference_label[old] == LABEL_CHANGED) >= 0.9
    new = (np.abs(scan[:, 1] - 1.96) < 0.01) & (scan[:, 0] > 2.5) & (scan[:, 0] < 2.85)
    assert np.mean(localisation.scan_label[new] == LABEL_CHANGED) >= 0.9


@pytest.mark.parametrize("seed", [1, 2])
def test_a_box_side_only_one_epoch_faced_next_to_a_change_of_the_other_stays_unseen(seed):
    # a box stands in both epochs and the scan never faced its +x side; the scan's box top,
    # which the reference saw too, meets that side and ends there.  A chair added beside the
    # box is a change of the scan's, but not the surface meeting the side: the side stays a
    # coverage difference
    rng = np.random.default_rng(seed)
    box = ([2.5, 1.5, 0.0], [3.0, 2.0, 0.6])
    reference = np.vstack([fused_room(rng, floor_hole=box), box_sides(rng, *box)])
    added = ([3.3, 1.0, 0.0], [3.7, 1.4, 0.9])
    scan = np.vstack(
        [
            fused_room(rng, floor_hole=([2.5, 1.0, 0.0], [3.7, 2.0, 0.0])),
            box_sides(rng, *box, faces="tnsw"),
            box_sides(rng, *added),
        ]
    )
    localisation = localise_changes(reference, scan)
    side = (np.abs(reference[:, 0] - 3.0) < 0.01) & (reference[:, 2] > 0.15)
    side &= (reference[:, 1] > 1.6) & (reference[:, 1] < 1.9) & (reference[:, 2] < 0.45)
    assert not np.any(localisation.reference_label[side] == LABEL_CHANGED)
    assert "added" in {region.kind for region in localisation.regions}


def test_a_board_and_the_floor_it_stands_on_are_two_surface_parts():
    # along a board's foot the normals of a fused map's points turn gradually from the
    # board's to the floor's (each fitted to neighbours on both): linked in steps of under 30
    # degrees, they chained the board to the floor into one part
    rng = np.random.default_rng(0)
    step = 0.01
    along, up = np.meshgrid(np.arange(0.0, 1.0, step), np.arange(0.0, 0.6, step))
    board = np.column_stack([np.zeros(along.size), along.ravel(), up.ravel()])
    along, out = np.meshgrid(np.arange(0.0, 1.0, step), np.arange(step, 0.6, step))
    floor = np.column_stack([-out.ravel(), along.ravel(), np.zeros(along.size)])
    # within 5 cm of the foot the normals lean towards each other, 40 degrees at most
    lean = np.radians(40.0) * np.clip(1.0 - board[:, 2] / 0.05, 0.0, 1.0)
    board_normal = np.column_stack([np.cos(lean), np.zeros(lean.size), np.sin(lean)])
    lean = np.radians(40.0) * np.clip(1.0 + floor[:, 0] / 0.05, 0.0, 1.0)
    floor_normal = np.column_stack([np.sin(lean), np.zeros(lean.size), np.cos(lean)])
    points = np.vstack([board, floor])
    points += rng.normal(0.0, 0.001, points.shape)
    labels = surface_parts(
        points, np.vstack([board_normal, floor_normal]), np.full(points.shape[0], 2.5 * step)
    )
    assert set(labels[: board.shape[0]]).isdisjoint(labels[board.shape[0] :])


def test_a_board_on_a_floor_patch_only_one_epoch_saw_is_changed():
    # RGB-D room 1002 of bench.moving_maps: a board standing in the open moved away.  The
    # scan's path never saw the floor on one side of the board's old place: that floor patch is
    # a coverage difference, and the board, chained to it along its foot, was one too (52 %)
    pair = map_pair("rgbd", change="moved", random_state=1002)
    reference, scan = pair.clouds()
    localisation = localise_changes(reference.points, scan.points)
    board = (pair.reference_change == 0) & pair.reference_changed & pair.reference_scored
    assert board.sum() > 1000
    assert np.mean(localisation.reference_label[board] == LABEL_CHANGED) >= 0.9


@pytest.mark.parametrize("seed", [1, 2])
def test_a_board_removed_from_a_desk_top_the_other_epoch_never_saw_is_changed(seed):
    # robot office 402 of bench.moving_maps: a board stood on a desk, its ends in line with
    # the desk's sides; the scan's lidar, under the desk top, saw the desk's sides but not its
    # top.  The desk's sides end under the board's foot: they met its border at an edge and
    # ended there, as an object's other sides would, and the board was an unseen side (3-9 %)
    rng = np.random.default_rng(seed)
    desk = ([2.0, 1.0, 0.0], [2.8, 1.8, 0.75])
    board = ([2.0, 1.4, 0.75], [2.8, 1.42, 1.4])
    reference = np.vstack(
        [
            fused_room(rng, floor_hole=desk),
            box_sides(rng, *desk, spacing=0.02),
            box_sides(rng, *board, faces="tsn", spacing=0.02),
        ]
    )
    scan = np.vstack(
        [fused_room(rng, floor_hole=desk), box_sides(rng, *desk, faces="nsew", spacing=0.02)]
    )
    localisation = localise_changes(reference, scan)
    on_board = (reference[:, 2] > 0.9) & (np.abs(reference[:, 1] - 1.41) < 0.02)
    on_board &= (reference[:, 0] > 2.0) & (reference[:, 0] < 2.8)
    assert np.mean(localisation.reference_label[on_board] == LABEL_CHANGED) >= 0.9


@pytest.mark.slow  # a whole drifting RGB-D room localised (~6 CPU s): make test-slow
def test_an_old_backrest_meeting_the_turned_one_at_a_smeared_corner_is_changed():
    # RGB-D room 1403 of bench.moving_maps (drift, misaligned; held out until s26, now a tuning
    # scene: the held-out RGB-D rooms are seeds 18 and up): a chair turned in
    # place.  The old backrest meets the turned one at the corner they share and ends there,
    # an unseen face (25 % of the chair changed), unless the surface meeting it carries on
    # into the scan's change.  The drift smears the turned backrest's corner: the 16 samples
    # nearest the old backrest's edge fit a diagonal plane no surface lies on, and the turned
    # backrest's changed points, off that plane, were never counted.  The surface meeting it
    # is the one most of its nearby samples' normals agree on: the turned backrest.
    pair = map_pair("rgbd", change="rotated", misaligned=True, random_state=1403, realism="drift")
    reference, scan = pair.clouds()
    rotation, shift = pair.true_transform[:3, :3], pair.true_transform[:3, 3]
    localisation = localise_changes(reference.points, scan.points @ rotation.T + shift)
    chair = (pair.reference_change == 0) & pair.reference_changed & pair.reference_scored
    assert chair.sum() > 400
    assert np.mean(localisation.reference_label[chair] == LABEL_CHANGED) >= 0.7


@pytest.mark.slow  # a whole RGB-D room localised (~5 CPU s): make test-slow
def test_an_old_backrest_meeting_the_turned_one_at_a_clean_corner_is_changed_too():
    # RGB-D room 803 of bench.moving_maps (clean, a tuning scene): a chair turned a quarter in
    # place.  At this clean corner the 16 samples nearest the old backrest's edge fit the
    # surface meeting it; the dominant fit among 64 (the smeared corner's, above) picks
    # another, and alone it left 80 % of the old chair changed.  Both fits are tried.
    pair = map_pair("rgbd", change="rotated", misaligned=True, random_state=803)
    reference, scan = pair.clouds()
    rotation, shift = pair.true_transform[:3, :3], pair.true_transform[:3, 3]
    localisation = localise_changes(reference.points, scan.points @ rotation.T + shift)
    found = total = 0  # the bench's recall: the chair's points of both epochs
    for label, change, changed, scored in (
        (
            localisation.reference_label,
            pair.reference_change,
            pair.reference_changed,
            pair.reference_scored,
        ),
        (localisation.scan_label, pair.scan_change, pair.scan_changed, pair.scan_scored),
    ):
        chair = (change == 0) & changed & scored
        total += np.count_nonzero(chair)
        found += np.count_nonzero(chair & (label == LABEL_CHANGED))
    assert total > 40
    assert found / total >= 0.9
