"""The map test's sampling gaps near a face's edge (issue 29, s27 robotquiet): a strip of a wall
or box face that both epochs saw in sample columns, next to the face's corner, lies between
the other epoch's columns on the face's plane."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.datasets.maps import map_pair
from app.core.localise.map_planes import in_sampling_gap, part_normals
from app.core.localise.surface import local_geometry
from app.core.pipeline import compare

COLUMN_STEP = 0.15
"""Vertical metres between a sample column's points, as a sparse robot map has them."""


def column(rng, x, y, *, low=0.0, high=2.7):
    """A vertical column of samples at (``x``, ``y``) with 8 mm of noise."""
    z = np.arange(low, high, COLUMN_STEP) + rng.uniform(0.0, COLUMN_STEP)
    z = z[z < high]
    points = np.column_stack([np.full(z.size, x), np.full(z.size, y), z])
    return points + rng.normal(0.0, 0.008, points.shape)


def corner(rng):
    """The other epoch near a corridor's corner: the side wall (y = 0) seen in columns up to
    x = -0.38, then nothing until the corner at x = 0, where the end wall (x = 0) runs on in
    columns every 5 cm."""
    side = [column(rng, x, 0.0) for x in (-0.9, -0.7, -0.52, -0.38)]
    end = [column(rng, 0.0, y) for y in np.arange(0.0, 1.0, 0.05)]
    return np.vstack(side + end)


def strip(rng):
    """This epoch's two columns of the side wall 12 and 17 cm from the corner."""
    return np.vstack(
        [column(rng, -0.17, 0.0, low=0.3, high=2.5), column(rng, -0.12, 0.0, low=0.3, high=2.5)]
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_thin_strip_of_a_wall_gets_its_parts_plane(seed):
    # robot corridor 3401: the strip's points' own normals ran along the wall (their
    # neighbours were their column, refitted round the corner onto the end wall)
    rng = np.random.default_rng(seed)
    points = strip(rng)
    along = np.tile([1.0, 0.0, 0.0], (points.shape[0], 1))
    planes = part_normals(points, np.zeros(points.shape[0], dtype=np.int64), along)
    assert np.all(np.abs(planes[:, 1]) > 0.95)
    # a part too small for a plane keeps its points' own normals
    few = part_normals(points[:3], np.zeros(3, dtype=np.int64), along[:3])
    assert np.array_equal(few, along[:3])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_wall_strip_beside_a_corner_lies_in_a_gap_of_the_other_epochs_wall(seed):
    rng = np.random.default_rng(seed)
    points = strip(rng)
    other = local_geometry(corner(rng), 10)
    along = np.tile([1.0, 0.0, 0.0], (points.shape[0], 1))
    labels = np.zeros(points.shape[0], dtype=np.int64)
    planes = part_normals(points, labels, along)
    # with its points' own normals (along the wall) no plane through them is the wall's
    assert np.mean(in_sampling_gap(points, along, other, 0.03)) < 0.5
    assert np.mean(in_sampling_gap(points, along, other, 0.03, planes)) >= 0.8


def test_a_box_face_in_front_of_a_wall_is_no_sampling_gap():
    # the guard: a box's face 0.3 m in front of the wall, which the other epoch has in columns
    # all round it, lies on no plane of the other epoch's: its part's plane finds no samples
    rng = np.random.default_rng(0)
    wall = np.vstack([column(rng, x, 0.0) for x in np.arange(-1.0, 1.0, 0.1)])
    other = local_geometry(wall, 10)
    face = np.vstack([column(rng, x, 0.3, high=0.6) for x in np.arange(-0.2, 0.2, 0.05)])
    planes = part_normals(face, np.zeros(face.shape[0], dtype=np.int64), face * 0.0 + [0, 1, 0])
    assert not in_sampling_gap(face, planes, other, 0.03, planes).any()


def test_held_out_unchanged_robot_corridor_3401_gets_no_region():
    # a 2.7 m strip of the corridor's side wall 5 cm wide, 14-19 cm from the end wall: the
    # reference's columns there are the corner's and 0.37 m back along the wall; every normal
    # of the strip ran along the wall: 1 `added` region of 31 points
    pair = map_pair("robot", layout="corridor", change="none", random_state=3401)
    result = compare(*pair.clouds())
    assert result.regions == []
