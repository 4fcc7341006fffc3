"""The map test's faces the other epoch saw in part (issue 29, s28 robot3405): a strip of a
box's face between the other epoch's columns of the same face and the box's outline (its top
edge, its side face) lies in a sampling gap; a removed box's face beside a standing one does
not."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from app.core.datasets.maps import map_pair
from app.core.labels import LABEL_CHANGED
from app.core.localise.map_outlines import inside_outline, outline_gap_share
from app.core.localise.map_planes import in_sampling_gap, part_normals
from app.core.localise.surface import local_geometry
from app.core.pipeline import compare

STEP = 0.04
"""Metres between samples along a scan column or line."""


def column(rng, x, y, low, high):
    """Vertical samples at (``x``, ``y``) from ``low`` to ``high`` with 5 mm of noise."""
    z = np.arange(low, high, STEP) + rng.uniform(0.0, STEP)
    z = z[z < high]
    points = np.column_stack([np.full(z.size, x), np.full(z.size, y), z])
    return points + rng.normal(0.0, 0.005, points.shape)


def level_lines(rng, z, xs, y_low, y_high):
    """Level samples at height ``z``: lines along y at each of ``xs``."""
    parts = []
    for x in xs:
        y = np.arange(y_low, y_high, STEP) + rng.uniform(0.0, STEP)
        y = y[y < y_high]
        parts.append(np.column_stack([np.full(y.size, x), y, np.full(y.size, z)]))
    return np.vstack(parts) + rng.normal(0.0, 0.005, (sum(p.shape[0] for p in parts), 3))


def rack_face(rng):
    """A rack's face 16 cm behind the box's back face (y = 0.16), columns every 12 cm: within
    0.5 m of the face's points most of the other epoch's samples are its."""
    return np.vstack([column(rng, x, 0.16, 0.0, 1.2) for x in np.arange(-1.0, 1.0, 0.12)])


def shelf(rng):
    """The shelf the box stands on (z = 0), from y = -1 to the rack face: it crosses the
    back face's plane."""
    return level_lines(rng, 0.0, np.arange(-1.0, 1.0, 0.08), -1.0, 0.15)


def box_seen_in_part(rng):
    """The other epoch's box (x -0.4..0.15, y -0.6..0, z 0..0.5): its back face (y = 0) in
    three columns at its left end only, its top, its side face x = 0.15 sampled up to 16 cm
    short of the back corner, the rack face and the shelf."""
    back = np.vstack([column(rng, x, 0.0, 0.0, 0.5) for x in (-0.37, -0.33, -0.29)])
    top = level_lines(rng, 0.5, np.arange(-0.38, 0.15, 0.06), -0.6, 0.0)
    side = np.vstack([column(rng, 0.15, y, 0.0, 0.5) for y in np.arange(-0.6, -0.16, 0.06)])
    return np.vstack([back, top, side, rack_face(rng), shelf(rng)])


def back_strip(rng):
    """This epoch's columns of the box's back face, between x = -0.15 and 0.07."""
    return np.vstack([column(rng, x, 0.0, 0.06, 0.45) for x in np.arange(-0.15, 0.08, 0.055)])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_box_face_strip_inside_the_other_epochs_outline_of_the_face(seed):
    # held-out robot warehouse 3405: the 32 nearest samples are the rack face's, so
    # in_sampling_gap says no (the main code's one false region of 34 points)
    rng = np.random.default_rng(seed)
    points = back_strip(rng)
    other = local_geometry(box_seen_in_part(rng), 10)
    normal = np.tile([0.0, 1.0, 0.0], (points.shape[0], 1))
    labels = np.zeros(points.shape[0], dtype=np.int64)
    planes = part_normals(points, labels, normal)
    assert np.mean(in_sampling_gap(points, normal, other, 0.03, planes)) < 0.5
    assert np.mean(inside_outline(points, normal, planes, other, 0.03)) >= 0.8
    share = outline_gap_share(
        points, normal, labels, np.array([True]), own=other, other=other, tolerance=0.03
    )
    assert share[0] >= 0.8


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_removed_boxs_face_beside_a_standing_face_is_outside(seed):
    # the other epoch lacks the box: the standing face in line with it on one side, the shelf
    # crossing under it, the rack behind; nothing of the box's top or side
    rng = np.random.default_rng(seed)
    points = back_strip(rng)
    standing = np.vstack([column(rng, x, 0.0, 0.0, 0.5) for x in (-0.37, -0.33, -0.29)])
    other = local_geometry(np.vstack([standing, rack_face(rng), shelf(rng)]), 10)
    normal = np.tile([0.0, 1.0, 0.0], (points.shape[0], 1))
    planes = part_normals(points, np.zeros(points.shape[0], dtype=np.int64), normal)
    assert not inside_outline(points, normal, planes, other, 0.03).any()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_face_the_other_epoch_has_no_samples_of_is_outside(seed):
    # the box's top and side seen, its back face nowhere: the face's own samples are the
    # evidence the other epoch saw it
    rng = np.random.default_rng(seed)
    points = back_strip(rng)
    seen = box_seen_in_part(rng)
    other = local_geometry(seen[np.abs(seen[:, 1]) > 0.03], 10)
    normal = np.tile([0.0, 1.0, 0.0], (points.shape[0], 1))
    planes = part_normals(points, np.zeros(points.shape[0], dtype=np.int64), normal)
    assert not inside_outline(points, normal, planes, other, 0.03).any()


def test_held_out_unchanged_robot_warehouse_3405_gets_no_region():
    # a box's back face 16 cm in front of a rack's face: the scan's columns of it 0.12-0.5 m to
    # one side of the reference's, its top edge above, its side face sampled 16 cm short of
    # the corner: 1 `removed` region of 34 points on the main code
    pair = map_pair("robot", layout="warehouse", change="none", random_state=3405)
    result = compare(*pair.clouds())
    assert result.regions == []


def rack_end(rng):
    """The other epoch at a rack's end face (x = 0, normal x): its columns of it at y 0.35-0.6,
    the rack's side face (y = -0.22) in columns running back from its corner, the floor."""
    face = np.vstack([column(rng, 0.0, y, 0.0, 2.0) for y in (0.35, 0.5, 0.55, 0.6)])
    side = np.vstack([column(rng, x, -0.22, 0.0, 2.0) for x in np.arange(-1.0, 0.01, 0.1)])
    floor = np.vstack([level_lines(rng, 0.0, np.arange(-1.0, 1.0, 0.1), -1.0, 1.0)[::2]])
    return np.vstack([face, side, floor])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_strip_of_a_rack_end_between_its_corner_and_the_other_epochs_columns(seed):
    # held-out robot warehouse 3804: this epoch's two columns of the end face between the
    # side's corner column and the other epoch's columns of the face 0.35 m off; the face's
    # plane comes from its samples' normals (a fit to their positions turns round a column)
    rng = np.random.default_rng(seed)
    points = np.vstack([column(rng, 0.0, y, 0.5, 1.5) for y in (0.0, 0.13)])
    other = local_geometry(rack_end(rng), 10)
    normal = np.tile([1.0, 0.0, 0.0], (points.shape[0], 1))
    planes = part_normals(points, np.zeros(points.shape[0], dtype=np.int64), normal)
    assert np.mean(inside_outline(points, normal, planes, other, 0.03)) >= 0.8


def test_held_out_robot_warehouse_3804_has_the_removed_board_only():
    # a strip of a rack's end face, 2 m tall and two columns wide, between the rack side's
    # corner and the reference's columns of the face: a false `added` region of 60 points on
    # the main code (IoU 0.649)
    pair = map_pair(
        "robot", layout="warehouse", change="removed", misaligned=True, random_state=3804
    )
    result = compare(*pair.clouds())
    assert [region.kind for region in result.regions] == ["removed"]


def rack_end_leaning(rng):
    """As :func:`rack_end`, the other epoch's end face in one strip of two close columns
    (y 0.40 and 0.44) whose fitted normals lean 11 degrees towards +y (fitted round to the
    surface beside it): their own samples lie 8 cm off the plane their normals give."""
    face = np.vstack([column(rng, 0.0, y, 0.0, 2.0) for y in (0.40, 0.44)])
    side = np.vstack([column(rng, x, -0.22, 0.0, 2.0) for x in np.arange(-1.0, 0.01, 0.1)])
    floor = level_lines(rng, 0.0, np.arange(-1.0, 1.0, 0.1), -1.0, 1.0)[::2]
    geometry = local_geometry(np.vstack([face, side, floor]), 10)
    normal = geometry.normal.copy()
    normal[: face.shape[0]] = [0.98, 0.2, 0.0] / np.hypot(0.98, 0.2)
    return dataclasses.replace(geometry, normal=normal)


WITHDRAWN_GUESSED_PLANE = (
    "s29 heldout's fix (the point's guessed plane tried as the face's plane) was withdrawn: it "
    "turned held-out robot 2300's rotated chair into coverage (recall 93 % -> 36 %)"
)


@pytest.mark.xfail(strict=True, reason=WITHDRAWN_GUESSED_PLANE)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_rack_end_strip_whose_other_columns_normals_lean(seed):
    # held-out unchanged robot warehouse 4305: the scan's one column of a rack's end face,
    # 0.3-0.4 m from the reference's columns, has normals 11 degrees off the face; the plane
    # they gave left the column itself 8 cm off it (no face: 0 % inside on the old code), and
    # the reference's columns were one `removed` region of 87 points
    rng = np.random.default_rng(seed)
    points = np.vstack([column(rng, 0.0, y, 0.5, 1.5) for y in (0.0, 0.13)])
    other = rack_end_leaning(rng)
    normal = np.tile([1.0, 0.0, 0.0], (points.shape[0], 1))
    planes = part_normals(points, np.zeros(points.shape[0], dtype=np.int64), normal)
    assert np.mean(inside_outline(points, normal, planes, other, 0.03)) >= 0.8


@pytest.mark.xfail(strict=True, reason=WITHDRAWN_GUESSED_PLANE)
def test_held_out_unchanged_robot_warehouse_4305_gets_no_region():
    # the reference's two columns of a rack's end face between the scan's one column 0.3-0.4 m
    # off (its normals leaning 11 degrees) and the rack side's corner: 1 `removed` region of
    # 87 points and a wrong decision on the main code
    pair = map_pair("robot", layout="warehouse", change="none", misaligned=True, random_state=4305)
    result = compare(*pair.clouds())
    assert result.regions == []


def test_held_out_robot_corridor_2300_keeps_its_rotated_chair():
    # a chair turned in place in a corridor: 93 % of its truly changed points are found; the
    # withdrawn guessed-plane outline (s29) closed the other epoch's outline round the chair's
    # faces and called 64 % of them coverage (recall 36 %, IoU 0.354)
    pair = map_pair(
        "robot", layout="corridor", change="rotated", misaligned=False, random_state=2300
    )
    result = compare(*pair.clouds())
    found = total = 0
    for label, changed, scored in (
        (result.reference_label, pair.reference_changed, pair.reference_scored),
        (result.scan_label, pair.scan_changed, pair.scan_scored),
    ):
        truly = changed & scored
        total += np.count_nonzero(truly)
        found += np.count_nonzero(truly & (label == LABEL_CHANGED))
    assert total > 100
    assert found / total >= 0.8
