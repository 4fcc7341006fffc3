"""Assertions about point clouds and their summaries."""

from __future__ import annotations

import numpy as np

from app.core.cloud import PointCloud
from app.core.cloud_summary import CloudSummary


def assert_summary_of(summary: CloudSummary, cloud: PointCloud) -> None:
    """``summary`` reports what ``cloud`` holds."""
    assert summary.n_source == cloud.n_source
    assert summary.n_points == len(cloud) and summary.n_dropped == cloud.n_dropped
    low, high = cloud.bounds()
    assert summary.low.dtype == np.float64 and summary.high.dtype == np.float64
    np.testing.assert_array_equal(summary.low, low)
    np.testing.assert_array_equal(summary.high, high)
    if cloud.sensor_origin is None:
        assert summary.sensor_origin is None
    else:
        np.testing.assert_array_equal(summary.sensor_origin, cloud.sensor_origin)
