"""The one whole-voxel subset of the origin searches (issue 28), its coverage at any density
(issue 30)."""

from __future__ import annotations

import numpy as np

from app.core.origins.voxels import (
    SAMPLE_EDGES,
    VOXEL_EDGE,
    VOXEL_POINTS,
    WholeVoxelSample,
    whole_voxels,
)


def floor_points(n_points: int, side: float, seed: int) -> np.ndarray:
    """``n_points`` random points on a ``side``-metre level floor (1 cm of height noise)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, side, size=(n_points, 2))
    return np.column_stack([xy, rng.normal(0.5, 0.01, n_points)])


def touched_cells(points: np.ndarray) -> int:
    """Distinct one-metre voxels holding some of ``points``."""
    return len(np.unique(np.floor(points).astype(np.int64), axis=0))


def test_the_subset_is_seeded_whole_voxels_of_about_the_size_asked():
    points = np.random.default_rng(3).uniform(-30.0, 30.0, size=(120_000, 3))
    first = whole_voxels(points, 20_000, np.random.default_rng(9))
    again = whole_voxels(points.copy(), 20_000, np.random.default_rng(9))
    other = whole_voxels(points, 20_000, np.random.default_rng(10))
    np.testing.assert_array_equal(first, again)
    assert not np.array_equal(first, other)
    assert 0.7 * 20_000 <= len(first) <= 1.3 * 20_000
    # sparse (under VOXEL_POINTS a voxel): VOXEL_EDGE voxels, each kept whole or not at all
    kept = {tuple(key) for key in np.floor(first / VOXEL_EDGE).astype(int).tolist()}
    in_kept = [tuple(key) in kept for key in np.floor(points / VOXEL_EDGE).astype(int).tolist()]
    assert int(np.count_nonzero(in_kept)) == len(first)


def test_a_small_cloud_is_kept_whole():
    points = floor_points(1_000, 10.0, 0)
    assert whole_voxels(points, 1_000, np.random.default_rng(0)) is points


def test_a_denser_cloud_is_covered_as_widely():
    """Eight times the density, the same subset size: the kept voxels spread over as much of
    the floor (one-metre voxels would be an eighth as many places)."""
    sparse = floor_points(VOXEL_POINTS // 2 * 400, 20.0, 1)
    dense = floor_points(VOXEL_POINTS * 4 * 400, 20.0, 2)
    max_points = len(sparse) // 10
    sparse_kept = whole_voxels(sparse, max_points, np.random.default_rng(4))
    dense_kept = whole_voxels(dense, max_points, np.random.default_rng(4))
    assert 0.7 * max_points <= len(dense_kept) <= 1.3 * max_points
    assert touched_cells(dense_kept) >= 0.6 * touched_cells(sparse_kept)


def block_share(subsets: list[np.ndarray]) -> float:
    """Share of all the points of ``subsets`` in the dense block of
    :func:`test_a_crowded_voxel_weighs_about_voxel_points`."""
    pooled = np.vstack(subsets)
    return float(np.mean(np.all((pooled[:, :2] >= 9.0) & (pooled[:, :2] <= 11.0), axis=1)))


def test_a_crowded_voxel_weighs_about_voxel_points():
    """A 2 x 2 m block a hundred times denser than the floor round it holds half the points:
    drawn whole, a large share of the subsets' points; thinned, about VOXEL_POINTS points a
    voxel of it (a few % of the subsets), and the floor's voxels are kept whole as before."""
    floor = floor_points(40_000, 20.0, 5)
    block = floor_points(40_000, 2.0, 6) + np.array([9.0, 9.0, 0.0])
    points = np.vstack([floor, block])
    seeds = [np.random.default_rng(seed) for seed in range(40)]
    plain = [whole_voxels(points, 8_000, np.random.default_rng(seed)) for seed in range(40)]
    thinned = [whole_voxels(points, 8_000, rng, thin_crowded=True) for rng in seeds]
    assert block_share(plain) > 0.15  # whole: the draw's luck, 0.2 of these 40
    assert block_share(thinned) < 0.05
    for whole, thin in zip(plain, thinned, strict=True):
        outside = whole[~np.all((whole[:, :2] >= 8.0) & (whole[:, :2] <= 12.0), axis=1)]
        kept = {tuple(row) for row in thin.tolist()}
        assert all(tuple(row) in kept for row in outside.tolist())


def test_a_sample_drawn_chunk_by_chunk_is_whole_voxels_at_the_density_s_edge():
    # a streamed file's sample (WholeVoxelSample): whole voxels, their edge shrunk with the
    # density as whole_voxels shrinks it, whatever the chunks
    for n_points in (20_000, 400_000):
        points = floor_points(n_points, 20.0, 4)
        sample = WholeVoxelSample(n_points, 10_000, random_state=2)
        for start in range(0, n_points, 7_919):
            sample.add(points[start : start + 7_919])
        kept = sample.points()
        assert 0.5 * 10_000 <= len(kept) <= 1.5 * 10_000
        edges = [edge for edge in SAMPLE_EDGES if edge**2 * n_points / 400.0 <= VOXEL_POINTS]
        edge = edges[0]  # the largest edge whose voxels hold at most VOXEL_POINTS points
        keys = {tuple(key) for key in np.floor(kept / edge).astype(int).tolist()}
        whole = [tuple(key) in keys for key in np.floor(points / edge).astype(int).tolist()]
        assert int(np.count_nonzero(whole)) == len(kept)  # every point of a kept voxel
        assert len(keys) >= 0.5 * 10_000 / VOXEL_POINTS  # as many places at either density
