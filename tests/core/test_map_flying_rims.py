"""The map test on fused RGB-D maps (issue 29): a fan of flying samples behind an object's rim
must not make the object's far side, seen by the other epoch only, a change.

Unchanged drifting RGB-D room 504 of ``bench.moving_maps`` (s24 rgbd504): a box each path saw
from its own side; the scan's depth-edge pixels behind the box's silhouette (a fused fan, not
isolated, so :mod:`app.core.localise.flying_samples` keeps them) are the scan's nearest points
to the border of the reference's east face and top.  They are surface the reference lacks, so
``map_surround.surrounded`` counts the border as surrounded (all 135 carried-on border points had
a flying nearest point), the face is no unseen side, and 1,256 of the box's reference points
are called removed.  Without the fan the same scene is unchanged (0 points here, and room 504
without flying pixels: the box's reference side unobserved).  Fixed in s25
(:mod:`app.core.localise.map_sides`): the fan stands in front of the east face, on the side
the reference saw it from (the scan's surface behind the face, its west face, tells the inner
side), in the air the reference looked through: no surface the box hid, and no surface
meeting the face at an edge (``map_surround.surrounded``, ``map_faces.far_faces``)."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from app.core.labels import LABEL_CHANGED
from app.core.localise import localise_changes
from tests.helpers.fused_rooms import box_sides, plane

BOX = ([2.5, 1.5, 0.0], [3.0, 2.1, 0.6])
"""A box standing in both epochs; the reference's path saw its east face and top, the
scan's its west and north faces."""
CAMERA = np.array([1.2, 1.8, 0.5])
"""The scan's camera, west of the box, at the height of its top."""
FAN = 400
"""Flying samples of the scan behind the box's silhouette (2 % of a room's points)."""
DENSE = 0.015
"""Metres: a fused RGB-D map's spacing (a 5-10 mm voxel map; flying samples stand out)."""


def _room(rng: np.random.Generator) -> NDArray[np.float64]:
    """A 5 x 4 m room's floor (less what the box hides) and two walls, densely sampled."""
    floor = plane(rng, [0, 0, 0], [5, 0, 0], [0, 4, 0], spacing=DENSE)
    low, high = BOX
    hidden = (
        (floor[:, 0] > low[0])
        & (floor[:, 0] < high[0])
        & (floor[:, 1] > low[1])
        & (floor[:, 1] < high[1])
    )
    walls = [
        plane(rng, [5, 0, 0], [0, 4, 0], [0, 0, 1.5], spacing=DENSE),
        plane(rng, [0, 4, 0], [5, 0, 0], [0, 0, 1.5], spacing=DENSE),
    ]
    return np.vstack([floor[~hidden], *walls])


def _fan(rng: np.random.Generator) -> NDArray[np.float64]:
    """Flying samples of the scan's camera: each on its line of sight past a point of the
    box's silhouette (its top's rims, its north-west edge), between the box and the floor
    or wall behind (a depth mixed of the two)."""
    low, high = (np.asarray(corner, float) for corner in BOX)
    rim = np.column_stack(
        [
            rng.choice([low[0], high[0]], FAN),
            rng.uniform(low[1], high[1], FAN),
            np.full(FAN, high[2]),
        ]
    )
    direction = rim - CAMERA
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    beyond = rng.uniform(0.02, 0.6, FAN)
    return rim + beyond[:, None] * direction


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_fan_of_flying_samples_behind_a_rim_is_no_hidden_surface(seed: int) -> None:
    rng = np.random.default_rng(seed)
    reference = np.vstack([_room(rng), box_sides(rng, *BOX, faces="ten", spacing=DENSE)])
    scan = np.vstack([_room(rng), box_sides(rng, *BOX, faces="wn", spacing=DENSE), _fan(rng)])
    localisation = localise_changes(reference, scan)
    assert localisation.parameters["reference_visibility"] == "maps"
    assert np.count_nonzero(localisation.reference_label == LABEL_CHANGED) == 0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_without_the_fan_the_box_seen_from_both_sides_is_unchanged(seed: int) -> None:
    # the guard of the test above: the same box and room, no flying samples
    rng = np.random.default_rng(seed)
    reference = np.vstack([_room(rng), box_sides(rng, *BOX, faces="ten", spacing=DENSE)])
    scan = np.vstack([_room(rng), box_sides(rng, *BOX, faces="wn", spacing=DENSE)])
    localisation = localise_changes(reference, scan)
    assert localisation.parameters["reference_visibility"] == "maps"
    assert np.count_nonzero(localisation.reference_label == LABEL_CHANGED) == 0
