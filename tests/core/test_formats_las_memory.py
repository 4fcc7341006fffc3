"""LAS/LAZ are decoded a chunk at a time into the cloud's one float64 array: reading a file
costs the cloud itself plus one chunk, never a second whole-cloud float64 copy (issue 30)."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from app.core.formats import las as las_module
from app.core.formats import read_point_cloud
from app.testing.files import las_bytes

N_POINTS = 400_000
CHUNK_POINTS = 20_000


@pytest.mark.parametrize("compress", [False, True])
def test_reading_las_costs_the_cloud_plus_one_chunk(tmp_path, monkeypatch, compress) -> None:
    monkeypatch.setattr(las_module, "CHUNK_POINTS", CHUNK_POINTS)
    points = np.random.default_rng(4).uniform(0.0, 40.0, size=(N_POINTS, 3))
    path = tmp_path / ("cloud.laz" if compress else "cloud.las")
    path.write_bytes(las_bytes(points, compress=compress, point_format=6, version="1.4"))
    tracemalloc.start()
    try:
        cloud = read_point_cloud(path, threads=1)
        held, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    np.testing.assert_allclose(cloud.points, points, atol=6e-4)
    whole_float64_copy = N_POINTS * 3 * 8
    assert held >= whole_float64_copy  # the cloud's own coordinates
    assert peak - held < whole_float64_copy / 2, (held, peak)
