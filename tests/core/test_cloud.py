"""PointCloud validation, source-order bookkeeping and local origin."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.cloud import MIN_POINTS, PointCloud, choose_local_origin
from app.core.errors import PointCloudError


def test_non_finite_rows_are_dropped_counted_and_keep_their_place():
    points = np.arange(60, dtype=float).reshape(20, 3)
    points[[2, 7]] = np.nan
    points[11, 1] = np.inf
    intensity = np.arange(20)
    cloud = PointCloud.from_array(points, attributes={"intensity": intensity})
    assert len(cloud) == 17 and cloud.n_dropped == 3 and cloud.n_source == 20
    assert 2 not in cloud.source_index and 11 not in cloud.source_index
    np.testing.assert_array_equal(cloud.attributes["intensity"], cloud.source_index)
    labels = cloud.to_source_order(np.ones(len(cloud), np.int8), fill=-1)
    assert labels.shape == (20,)
    assert list(np.flatnonzero(labels == -1)) == [2, 7, 11]


def test_labels_in_file_order_come_back_aligned_with_the_points():
    points = np.arange(12, dtype=float).reshape(4, 3)
    points[1] = np.nan  # a dropped row keeps its place in file-order labels
    cloud = PointCloud.from_array(points, min_points=1)
    labels = np.array([0, -1, 1, 0], dtype=np.int8)
    assert cloud.from_source_order(labels).tolist() == [0, 1, 0]
    np.testing.assert_array_equal(
        cloud.from_source_order(cloud.to_source_order(np.array([5, 6, 7]), fill=-1)), [5, 6, 7]
    )
    with pytest.raises(ValueError, match="another file"):
        cloud.from_source_order(labels[:2])


@pytest.mark.parametrize(
    ("points", "fragment"),
    [
        (np.zeros((0, 3)), "empty"),
        (np.full((30, 3), np.nan), "none of the 30 points"),
        (np.zeros((MIN_POINTS - 1, 3)), f"at least {MIN_POINTS}"),
        (np.zeros((30, 2)), "shape (n, 3)"),
        (np.array([["a", "b", "c"]] * 20), "not numbers"),
    ],
)
def test_unusable_clouds_raise_point_cloud_error(points, fragment):
    with pytest.raises(PointCloudError, match=None) as error:
        PointCloud.from_array(points)
    assert fragment in str(error.value)


def test_attribute_with_wrong_length_is_rejected():
    with pytest.raises(PointCloudError, match="attribute 'rgb'"):
        PointCloud.from_array(np.zeros((20, 3)), attributes={"rgb": np.zeros(19)})


def test_local_origin_keeps_millimetres_for_georeferenced_data():
    rng = np.random.default_rng(0)
    local = rng.uniform(-50, 50, size=(1000, 3))
    georeferenced = local + np.array([512_345.678, 5_412_345.678, 250.0])
    origin = choose_local_origin(georeferenced)
    assert np.all(np.abs(origin - georeferenced.mean(axis=0)) < 100)
    shifted = (georeferenced - origin).astype(np.float32)  # what a float32 consumer sees
    np.testing.assert_allclose(shifted + origin, georeferenced, atol=1e-4)
    np.testing.assert_array_equal(choose_local_origin(local), np.zeros(3))
