"""The spatial (Z-order) query order: a permutation, and the same answers as file order."""

from __future__ import annotations

import numpy as np
from pykdtree.kdtree import KDTree

from app.core.localise.distance import nearest_in
from app.core.localise.neighbourhoods import nearest_neighbourhoods
from app.core.localise.surface import local_geometry, neighbourhood_planes
from app.core.spatial_order import ordered_chunks, spatial_order


def _shuffled_surfaces(n_points: int, seed: int) -> np.ndarray:
    """Points on three planes of a 10 m room, far from the origin, in random order."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform(0.0, 10.0, (n_points, 2))
    face = rng.integers(0, 3, n_points)
    points = np.zeros((n_points, 3))
    points[face == 0] = np.column_stack([uv[face == 0], np.zeros(np.sum(face == 0))])
    points[face == 1] = np.column_stack([np.zeros(np.sum(face == 1)), uv[face == 1]])
    points[face == 2, 0] = uv[face == 2, 0]
    points[face == 2, 2] = uv[face == 2, 1]
    points += rng.normal(0.0, 0.003, points.shape)
    points += np.array([512_000.0, 4_300_000.0, 80.0])
    return points


def test_spatial_order_is_a_permutation_that_keeps_neighbours_together():
    points = _shuffled_surfaces(20_000, seed=1)
    order = spatial_order(points)
    assert np.array_equal(np.sort(order), np.arange(len(points)))
    step_in_order = np.linalg.norm(np.diff(points[order], axis=0), axis=1)
    step_in_file = np.linalg.norm(np.diff(points, axis=0), axis=1)
    assert np.median(step_in_order) < np.median(step_in_file) / 10


def test_spatial_order_of_degenerate_clouds():
    assert spatial_order(np.empty((0, 3))).shape == (0,)
    same = np.ones((5, 3))
    assert np.array_equal(np.sort(spatial_order(same)), np.arange(5))


def test_ordered_chunks_cover_every_row_once():
    order = np.random.default_rng(2).permutation(1000)
    rows = np.concatenate(list(ordered_chunks(order, 1000, 128)))
    assert np.array_equal(np.sort(rows), np.arange(1000))
    slices = list(ordered_chunks(None, 1000, 300))
    assert slices[0] == slice(0, 300) and slices[-1] == slice(900, 1200)


def test_queries_in_spatial_order_give_the_file_order_answers():
    points = _shuffled_surfaces(30_000, seed=3)
    found = nearest_neighbourhoods(points, 10)
    distance, index = KDTree(points).query(points, k=11)
    assert np.array_equal(found.neighbor_index, index)
    assert np.array_equal(found.kth_distance, distance[:, 10])
    in_file_order = neighbourhood_planes(points, found.neighbor_index)
    in_spatial_order = neighbourhood_planes(points, found.neighbor_index, found.order)
    for file_value, spatial_value in zip(in_file_order, in_spatial_order, strict=True):
        assert np.array_equal(file_value, spatial_value)


def test_nearest_in_spatial_order_gives_the_file_order_answers():
    reference = _shuffled_surfaces(20_000, seed=4)
    scan = _shuffled_surfaces(15_000, seed=5)
    geometry = local_geometry(reference, 10)
    plain_distance, plain_index = nearest_in(scan, geometry)
    ordered_distance, ordered_index = nearest_in(scan, geometry, spatial_order(scan))
    assert np.array_equal(plain_distance, ordered_distance)
    assert np.array_equal(plain_index, ordered_index)
