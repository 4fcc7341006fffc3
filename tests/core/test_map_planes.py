"""The map test's plane probes (``map_planes.share_on_planes``): a patch of a wall whose
points' own planes are tilted by the corners round them, or offset by noise, still lies on
the other epoch's sparse samples of the same wall a metre away."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.localise.map_planes import share_on_planes
from app.core.localise.rays import Candidates
from app.core.localise.surface import local_geometry
from tests.helpers.fused_rooms import plane

TOLERANCE = 0.025


def _candidates(points: np.ndarray, normal: np.ndarray) -> Candidates:
    count = points.shape[0]
    return Candidates(
        index=np.arange(count),
        points=points,
        normal=normal.astype(np.float32),
        linear=np.zeros(count, dtype=bool),
        spacing=np.full(count, 0.02),
        surface_distance=np.full(count, 0.3),
    )


def _tilted(rng: np.random.Generator, normal: np.ndarray, degrees: float) -> np.ndarray:
    """``normal`` (n, 3) turned by ``degrees`` about the vertical, either way at random."""
    angle = np.radians(degrees) * rng.choice([-1.0, 1.0], normal.shape[0])
    turned = normal * np.cos(angle)[:, None]
    turned[:, 1] += np.sin(angle)
    return turned / np.linalg.norm(turned, axis=1, keepdims=True)


@pytest.mark.parametrize("seed", range(3))
def test_a_wall_patch_with_tilted_point_normals_lies_on_the_other_epochs_wall(seed):
    """The patch (x = 0, y 1.0-1.8, z 0-0.8) is 1 m beside the other epoch's sparse samples
    of the same wall (y 0-0.5); its points' normals are tilted 6 degrees (the floor and the
    corner in their neighbourhoods) and its samples lie 0-3 cm off the wall.  Main found the
    other epoch's samples on 0-40 % of the patch's planes (60 cm off a tilted plane at 1 m);
    on the patch's own plane, all of them."""
    rng = np.random.default_rng(seed)
    wall = plane(rng, [0, 0, 0], [0, 0.5, 0], [0, 0, 0.8], spacing=0.05)
    patch = plane(rng, [0, 1.0, 0], [0, 0.8, 0], [0, 0, 0.8], spacing=0.02)
    patch[:, 0] += rng.uniform(-0.03, 0.03, patch.shape[0])
    normal = _tilted(rng, np.tile([1.0, 0.0, 0.0], (patch.shape[0], 1)), 6.0)
    labels = np.zeros(patch.shape[0], dtype=np.int64)
    share = share_on_planes(
        _candidates(patch, normal), labels, 1, local_geometry(wall, 10), TOLERANCE, 0.1
    )
    assert share[0] >= 0.9


def test_a_face_off_the_other_epochs_plane_stays_off_it():
    """A box face 20 cm before the same wall, its samples 0-3 cm off its plane: on the
    other epoch's plane neither point by point nor on its own plane."""
    rng = np.random.default_rng(0)
    wall = plane(rng, [0, 0, 0], [0, 0.5, 0], [0, 0, 0.8], spacing=0.05)
    face = plane(rng, [0.2, 1.0, 0], [0, 0.8, 0], [0, 0, 0.8], spacing=0.02)
    face[:, 0] += rng.uniform(-0.03, 0.03, face.shape[0])
    normal = np.tile([1.0, 0.0, 0.0], (face.shape[0], 1))
    labels = np.zeros(face.shape[0], dtype=np.int64)
    share = share_on_planes(
        _candidates(face, normal), labels, 1, local_geometry(wall, 10), TOLERANCE, 0.1
    )
    assert share[0] == 0.0
