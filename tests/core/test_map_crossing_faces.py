"""A surface of the other epoch crossing a part's plane, partly surface this epoch lacks (issue 29).

Robot warehouse 2104 of ``bench.moving_maps``: a box turned a quarter in place.  The new box's
long side stands out past the old box's side; the reference sampled that old side sparsely:
just outside the new side (within the change threshold of it, matched, and farther out,
lacking) and inside the new box (lacking).  The map test took the new side's end for an unseen
face, the old side ending at it.  The old side carries on through the new side: surface the
scan lacks on both sides of the new side's plane (``map_planes.through_lacking``).

Drifting RGB-D room 504 (unchanged): the scan's copy of a box, 12 cm off and 6 cm higher than
the reference's, has its side (surface the reference lacks below the reference's top) end
6 cm above the reference's top, a sample matched by the reference's top: the side ends at its
own top edge, it does not cross the reference's top."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from pykdtree.kdtree import KDTree

from app.core.localise.map_planes import SECTORS
from app.core.localise.map_surround import SURROUND_SECTORS, surrounded

CHANGE_THRESHOLD = 0.1


def _grid(rng, xs, ys, zs, noise=0.003):
    """Points on the grid of ``xs`` x ``ys`` x ``zs`` (one of them a single value), jittered."""
    grid = np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), axis=-1).reshape(-1, 3)
    return grid + rng.normal(0.0, noise, grid.shape)


def _geometry(points, normal):
    """A cloud's geometry as the map test's steps read it: one normal for all points."""
    normal = np.tile(np.asarray(normal, np.float32), (points.shape[0], 1))
    return SimpleNamespace(points=points, normal=normal, tree=KDTree(points))


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize(
    ("columns", "carried"),
    [
        # the old side of a turned box: outside the face at 7 cm (matched) and 15 cm
        # (lacking), inside it at 15-20 cm (lacking): it crosses the face
        ([0.07, 0.15, -0.15, -0.2], True),
        # the same object's other face, ending at this face: outside it only
        ([0.07, 0.12], False),
        # a drifted copy of the same object: its face, lacking inside this face, ends 6 cm
        # past it, at a sample this epoch's face matches (drifting RGB-D room 504)
        ([0.06, -0.09, -0.15, -0.2], False),
    ],
)
def test_a_surface_lacking_on_both_sides_of_a_face_carries_on_past_it(seed, columns, carried):
    # the other epoch's side (plane y = 0) sampled sparsely in ``columns`` (x) and two rows,
    # this epoch's face on the plane x = 0 (normal x), the border point 10 cm off that side;
    # a sample is surface this epoch lacks when more than c from the face
    rng = np.random.default_rng(seed)
    other_points = _grid(rng, columns, [0.0], [0.44, 0.62])
    other = _geometry(other_points, [0.0, 1.0, 0.0])
    lacking = np.abs(other_points[:, 0]) > CHANGE_THRESHOLD
    point = np.array([[0.0, -0.1, 0.5]])

    adjoining, sectors, _ = surrounded(
        point,
        np.array([[1.0, 0.0, 0.0]], np.float32),
        other,  # type: ignore[arg-type]
        lacking,
        tolerance=0.01,
        change_threshold=CHANGE_THRESHOLD,
        inward=np.zeros((1, 2, 3)),
    )

    assert adjoining[0]
    assert bool(sectors[0] >= SURROUND_SECTORS) == carried
    if carried:
        assert sectors[0] == SECTORS
