"""The compiled plane fit (``app/core/localise/_plane_kernel.c``, built by setup.py where a C
compiler is) against the numpy passes it replaces and that run without it: the same bits, the
same labels; arrays it cannot read are refused or left to numpy."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.cloud import PointCloud
from app.core.datasets.lidar import lidar_pair
from app.core.datasets.scenes import raycast_scene
from app.core.localise import surface
from app.core.localise.neighbourhoods import nearest_neighbourhoods
from app.core.pipeline import compare
from tests.helpers.environment import c_compiler_found

KERNEL = surface.PLANE_KERNEL
needs_kernel = pytest.mark.skipif(KERNEL is None, reason="installed without a C compiler")


@pytest.fixture(scope="module")
def lidar_points():
    """A single-station room (~28k points): floors at grazing angles give line-shaped
    neighbourhoods, hence the wide refit too."""
    return lidar_pair(layout="room", angular_step_deg=1.2, random_state=5).reference


def assert_same_bits(compiled: tuple, plain: tuple) -> None:
    assert len(compiled) == len(plain)
    for first, second in zip(compiled, plain, strict=True):
        assert first.dtype == second.dtype and first.shape == second.shape
        assert np.array_equal(first.view(np.uint8), second.view(np.uint8))


def test_the_kernel_is_built_where_a_c_compiler_is():
    if not c_compiler_found():
        pytest.skip("no C compiler: the numpy passes run")
    assert KERNEL is not None, "setup.py builds app.core.localise._plane_kernel: reinstall"


@needs_kernel
@pytest.mark.parametrize("n_neighbors", [10, 30])
def test_planes_are_the_numpy_passes_to_the_bit(lidar_points, n_neighbors, monkeypatch):
    found = nearest_neighbourhoods(lidar_points, n_neighbors)
    index = found.neighbor_index
    compiled = surface.neighbourhood_planes(lidar_points, index, found.order, threads=2)
    in_file_order = surface.neighbourhood_planes(np.asfortranarray(lidar_points), index)
    monkeypatch.setattr(surface, "PLANE_KERNEL", None)
    plain = surface.neighbourhood_planes(lidar_points, index, found.order)
    assert_same_bits(compiled, plain)
    assert_same_bits(in_file_order, plain)


@needs_kernel
def test_degenerate_neighbourhoods_are_the_numpy_passes_to_the_bit(monkeypatch):
    rng = np.random.default_rng(2)
    points = np.concatenate(
        [
            np.zeros((6, 3)),  # one point six times: no spread, the normal (0, 0, 1)
            np.outer(np.arange(6.0), [0.3, -0.2, 0.1]),  # a line
            rng.normal(size=(6, 3)) * [1.0, 1.0, 0.0],  # a plane
            rng.normal(size=(6, 3)),  # a blob
        ]
    )
    index = np.arange(24, dtype=np.uint32).reshape(4, 6)
    compiled = surface.neighbourhood_planes(points, index)
    monkeypatch.setattr(surface, "PLANE_KERNEL", None)
    plain = surface.neighbourhood_planes(points, index)
    assert_same_bits(compiled, plain)
    assert np.array_equal(compiled[0][0], [0.0, 0.0, 1.0])


@needs_kernel
def test_wide_neighbourhoods_are_the_numpy_passes_to_the_bit(monkeypatch):
    """More than 128 neighbours: numpy's pairwise sums split in halves (any n_neighbors is
    allowed, and line-shaped neighbourhoods are refitted with three times as many)."""
    rng = np.random.default_rng(4)
    points = rng.normal(size=(1500, 3)) * [3.0, 2.0, 0.01] + 1000.0
    index = np.stack([rng.permutation(1500)[:1201] for _ in range(7)]).astype(np.uint32)
    compiled = surface.neighbourhood_planes(points, index)
    values = rng.random(1500)
    compiled_means = surface._neighbourhood_means(values, index, None, 1)
    monkeypatch.setattr(surface, "PLANE_KERNEL", None)
    assert_same_bits(compiled, surface.neighbourhood_planes(points, index))
    assert np.array_equal(compiled_means, surface._neighbourhood_means(values, index, None, 1))


@needs_kernel
def test_surfaces_and_labels_are_the_numpy_passes(lidar_points, monkeypatch):
    found = nearest_neighbourhoods(lidar_points, 10)
    arguments = (lidar_points, found.tree, found.neighbor_index, found.kth_distance, found.order)
    pair = raycast_scene(n_points=20_000, change="box", random_state=3)
    clouds = (
        PointCloud.from_array(pair.reference, sensor_origin=pair.reference_origin),
        PointCloud.from_array(pair.scan, sensor_origin=pair.scan_origin),
    )
    compiled = surface.fit_surfaces(*arguments, threads=2)
    compiled_result = compare(*clouds)
    monkeypatch.setattr(surface, "PLANE_KERNEL", None)
    plain = surface.fit_surfaces(*arguments)
    plain_result = compare(*clouds)
    assert compiled.noise == plain.noise and compiled.linear.any()
    for name in ("normal", "plane_constant", "spacing", "linear", "variation"):
        assert np.array_equal(getattr(compiled, name), getattr(plain, name)), name
    assert np.count_nonzero(compiled_result.scan_label == 1) > 0
    for name in ("reference_label", "scan_label", "reference_distance", "scan_distance"):
        assert np.array_equal(
            getattr(compiled_result, name), getattr(plain_result, name), equal_nan=True
        ), name
    assert compiled_result.score == plain_result.score


@needs_kernel
def test_arrays_the_kernel_cannot_read_are_refused_or_left_to_numpy(monkeypatch):
    points = np.random.default_rng(3).normal(size=(40, 3))
    index = nearest_neighbourhoods(points, 5).neighbor_index
    moments = np.empty((12, 40))
    rows = np.arange(40, dtype=np.int64)
    with pytest.raises(TypeError, match="neighbor_index"):
        KERNEL.plane_moments(points, index.astype(np.int64), rows, moments)
    with pytest.raises(TypeError, match="points"):
        KERNEL.plane_moments(points.astype(np.float32), index, rows, moments)
    with pytest.raises(ValueError, match="moments"):
        KERNEL.plane_moments(points, index, rows, np.empty((12, 10)))
    outside = index.copy()
    outside[7, 2] = 40
    with pytest.raises(IndexError, match=r"outside 0\.\.39"):
        KERNEL.plane_moments(points, outside, rows, moments)
    with pytest.raises(IndexError, match="outside"):
        KERNEL.neighbourhood_means(points[:, 0].copy(), index, rows + 1, np.empty(40))
    # an int64 index or float32 points: the numpy passes, the same planes
    compiled = surface.neighbourhood_planes(points, index.astype(np.int64))
    monkeypatch.setattr(surface, "PLANE_KERNEL", None)
    assert_same_bits(compiled, surface.neighbourhood_planes(points, index))
