"""Which side of a surface part its epoch saw it from (issue 29,
:mod:`app.core.localise.map_sides`): the other epoch's surface behind the part tells its inner
side, and samples off the part on the other side stand in the air in front of it."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.localise.distance import Side
from app.core.localise.map_sides import in_front, inner_sides, nearest_in_air
from app.core.localise.surface import local_geometry
from tests.helpers.fused_rooms import plane

DENSE = 0.015


def _side(points: np.ndarray) -> Side:
    nowhere = np.zeros(points.shape[0])
    return Side("scan", "added", points, None, local_geometry(points, 10), nowhere, nowhere)


def _face(rng: np.random.Generator) -> np.ndarray:
    """A box's east face at x = 3 (0.6 x 0.6 m), the part."""
    return plane(rng, [3.0, 1.5, 0.0], [0, 0.6, 0], [0, 0, 0.6], spacing=DENSE)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_surface_behind_a_face_tells_its_inner_side(seed: int) -> None:
    rng = np.random.default_rng(seed)
    face = _face(rng)
    # the other epoch's far face of the box, 0.5 m behind (west), surface this epoch lacks
    far = plane(rng, [2.5, 1.5, 0.0], [0, 0.6, 0], [0, 0, 0.6], spacing=DENSE)
    other = _side(far)
    labels = np.zeros(face.shape[0], dtype=np.int64)
    normal = np.tile([1.0, 0.0, 0.0], (face.shape[0], 1))
    inward = inner_sides(face, normal, labels, np.array([True]), other, np.ones(len(far), bool))
    assert np.allclose(np.abs(inward[:, 0, 0]), 1.0)
    assert np.all(inward[:, 0, 0] < 0)  # into the box: west
    assert np.allclose(inward[:, 1], 0.0)  # no level candidates: no side known
    # a sample 4 cm east of the face is in front of it, one 4 cm west behind it
    offsets = np.array([[0.04, 0.0, 0.1], [-0.04, 0.0, 0.1]])
    assert in_front(offsets, inward[:2], 0.01).tolist() == [True, False]
    # nothing behind: no side known, nothing in front
    unknown = inner_sides(face, normal, labels, np.array([True]), other, np.zeros(len(far), bool))
    assert np.allclose(unknown, 0.0)
    assert not in_front(offsets, unknown[:2], 0.01).any()


def test_a_sample_in_the_air_in_front_of_the_face_is_told_from_one_behind_it() -> None:
    rng = np.random.default_rng(0)
    # three samples of the other epoch near the face: this epoch lacks the first two, 5 cm
    # in front of the face (east) and 5 cm behind it; it has the third, in front
    samples = np.array([[3.05, 1.6, 0.3], [2.95, 1.8, 0.3], [3.05, 2.0, 0.3]])
    other = _side(np.vstack([samples, plane(rng, [6, 0, 0], [0, 1, 0], [0, 0, 1], DENSE)]))
    counted = np.zeros(other.points.shape[0], dtype=bool)
    counted[:2] = True
    inward = np.zeros((3, 2, 3))
    inward[:, 0] = [-1.0, 0.0, 0.0]
    points = np.array([[3.0, 1.6, 0.3], [3.0, 1.8, 0.3], [3.0, 2.0, 0.3]])
    assert nearest_in_air(points, inward, other, counted, 0.01).tolist() == [True, False, False]
