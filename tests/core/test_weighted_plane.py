"""``weighted_plane``: the weighted centroid and scatter shared by the surface-offset probe
(``surface_levels.surface_offset_candidates``) and the far-face test's meeting planes
(``map_faces``)."""

from __future__ import annotations

import numpy as np

from app.core.localise.surface import weighted_plane


def test_a_tilted_plane_is_found_with_the_points_weighted_out_left_out():
    rng = np.random.default_rng(0)
    normal = np.array([0.3, -0.2, 0.93])
    normal /= np.linalg.norm(normal)
    first = np.cross(normal, [1.0, 0.0, 0.0])
    first /= np.linalg.norm(first)
    second = np.cross(normal, first)
    along = rng.uniform(-0.5, 0.5, (4, 20, 2))
    positions = 2.0 + along[..., :1] * first + along[..., 1:] * second
    weight = np.ones((4, 20))
    positions[:, :5] += rng.uniform(0.3, 0.6, (4, 5, 3))  # far off the plane
    weight[:, :5] = 0.0
    centroid, values, vectors = weighted_plane(positions, weight)
    assert np.allclose(np.abs(vectors[:, :, 0] @ normal), 1.0, atol=1e-9)
    assert np.allclose(centroid, positions[:, 5:].mean(axis=1))
    assert np.all(values[:, 0] < 1e-9) and np.all(values[:, 1] > 1e-3)
    # the weights' scale does not matter; a set weighted out entirely stays finite
    scaled = weighted_plane(positions, 7.0 * weight)
    assert np.allclose(scaled[0], centroid) and np.allclose(scaled[1], values)
    empty = weighted_plane(positions[:1], np.zeros((1, 20)))
    assert all(np.all(np.isfinite(part)) for part in empty)
