"""The map test on metric-scale planes (issue 29): a dense, noisy fused map's normals are
fitted over a few centimetres whatever its density; a sparse map keeps its own fits."""

from __future__ import annotations

import numpy as np

from app.core.labels import LABEL_CHANGED
from app.core.localise import localise_changes
from app.core.localise.distance import Side
from app.core.localise.map_scale import metric_planes, metric_side
from app.core.localise.surface import local_geometry
from tests.helpers.fused_rooms import box_removed_beside_a_band, plane

SPACING, WALL_NOISE = 0.008, 0.012
"""Finer than the rooms of ``test_map_fragments`` (8 mm, as a 5-10 mm voxel-thinned RGB-D
map), with 1.2 cm of noise on the wall."""


def _wall_room(rng, wall_top):
    """A 2.5 x 2 m floor and a noisy wall at y = 2 up to ``wall_top`` metres."""
    return np.vstack(
        [
            plane(rng, [0, 0, 0], [2.5, 0, 0], [0, 2.0, 0], spacing=SPACING, noise=0.004),
            plane(rng, [0, 2.0, 0], [2.5, 0, 0], [0, 0, wall_top], SPACING, WALL_NOISE),
        ]
    )


def _side(points):
    geometry = local_geometry(points, 10)
    nowhere = np.zeros(points.shape[0])
    return Side("reference", "removed", points, None, geometry, nowhere, nowhere.astype(np.uint32))


def test_a_dense_wall_band_one_path_saw_is_no_change():
    """The reference saw the wall up to 2.4 m, the scan up to 1.4 m, 8 mm apart: main (10
    neighbours' normals) called the whole band above 1.4 m changed (35,236 points)."""
    rng = np.random.default_rng(1)
    reference, scan = _wall_room(rng, 2.4), _wall_room(rng, 1.4)
    found = localise_changes(reference, scan, threads=1)
    assert found.regions == []
    assert np.count_nonzero(found.reference_label == LABEL_CHANGED) == 0
    assert np.count_nonzero(found.scan_label == LABEL_CHANGED) == 0


def test_a_removed_box_beside_a_dense_band_is_still_found():
    share, elsewhere = box_removed_beside_a_band(np.random.default_rng(1), _wall_room, SPACING)
    assert share >= 0.9
    assert elsewhere == 0


def test_a_dense_noisy_wall_gets_its_own_normal():
    """10 neighbours 8 mm apart with 1.2 cm of noise: half the normals tilt by more than 30
    degrees (0.53 measured); the metric planes, ~5 cm across, 2 % (0.02)."""
    rng = np.random.default_rng(0)
    wall = plane(rng, [0, 0, 0], [2.0, 0, 0], [0, 0, 2.0], SPACING, WALL_NOISE)
    side = _side(wall)
    steep = np.cos(np.radians(30))
    metric, normal = metric_side(side, metric_planes(side))
    assert normal is not None
    assert np.mean(np.abs(side.geometry.normal[:, 1]) < steep) > 0.4
    assert np.mean(np.abs(normal[:, 1]) < steep) < 0.05
    assert np.allclose(metric.geometry.normal, normal)
    offset = np.einsum("nd,nd->n", wall, normal) - metric.geometry.plane_constant
    assert np.percentile(np.abs(offset), 95) < 4 * WALL_NOISE


def test_a_sparse_map_keeps_its_own_fits():
    """A robot map's 3-5 cm samples: its 10 neighbours' normals are its surfaces' axes."""
    rng = np.random.default_rng(0)
    side = _side(plane(rng, [0, 0, 0], [3.0, 0, 0], [0, 3.0, 0], spacing=0.04, noise=0.008))
    metric, normal = metric_side(side, metric_planes(side))
    assert normal is None
    assert metric is side
