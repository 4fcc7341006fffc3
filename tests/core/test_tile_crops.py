"""Each tile's crop written to files of its own in one pass (app.core.tiling.crops), for a
moving-sensor map (rays from a trajectory).

A tile computed from its crop files must equal the tile computed from the whole pair: the same
points in the same order, the same stations and rays, so the merged comparison is identical.
Small chunks make the pass cut the clouds at many places.  make test runs the merged-station
case (tests/core/test_tiling.py, on its module's pair); this one is in make test-slow.  The
records are packed and narrow; the direction marks from chunks are the whole cloud's.
"""

from __future__ import annotations

import numpy as np
import pytest

from app.core.datasets.maps import map_pair
from app.core.tiling.compare import compare_tiled
from app.core.tiling.crops import MARK_PARTS, box_direction_marks, record_dtype
from app.core.tiling.rays import box_mask, crop_mask, direction_marks, own_direction_cells
from tests.helpers.tiling import CropChecker, assert_identical_results


@pytest.mark.slow
def test_a_tiled_comparison_of_a_map_from_crop_files_equals_the_whole_pairs(tmp_path) -> None:
    pair = map_pair("robot", change="mixed", size=0.6, random_state=1)
    reference, scan = pair.reference, pair.scan
    options = {
        "budget_bytes": 1 << 40,
        "max_crop_points": int(0.55 * (len(reference) + len(scan))),
        "margin": 1.0,
        "ray_reach": 4.0,
        "threads": 1,
    }
    checker = CropChecker(tmp_path / "crops")
    from_files = compare_tiled(reference, scan, run_tiles=checker, **options)
    in_process = compare_tiled(reference, scan, **options)
    assert len(checker.crop_sizes) >= 2, "several tiles"
    assert checker.rays_seen
    assert in_process.regions, "the scene has changes"
    assert max(checker.crop_sizes) < 0.9 * (len(reference) + len(scan)), "no tile holds all"
    assert_identical_results(from_files, in_process)


def test_crop_records_are_packed_and_as_narrow_as_the_cloud_allows() -> None:
    # a crop record: float32 point, uint32 index below 2**32 points, int8 station up to 127
    float32 = np.zeros((0, 3), np.float32)
    record = record_dtype(float32, 2**32 - 1, 127)
    assert (record.itemsize, record["index"], record["station"]) == (17, np.uint32, np.int8)
    assert record_dtype(float32, 2**32, 5)["index"] == np.int64
    assert record_dtype(float32, 1000, 128)["station"] == np.int16
    assert record_dtype(float32, 1000, None).itemsize == 16


def test_direction_marks_joined_as_the_chunks_come_are_the_whole_clouds() -> None:
    # the chunks' cells of a box are joined every few chunks (the same cell held once): the
    # marks are those of the box's points taken at once
    generator = np.random.default_rng(5)
    points = generator.uniform(-6.0, 6.0, size=(5000, 3)).astype(np.float32)
    origins = np.array([[0.0, 0.0, 1.5], [3.0, -2.0, 1.0]])
    cells = np.array([0.05, 0.08])
    low, high = np.array([-1.0, -2.0]), np.array([2.5, 1.0])
    whole = direction_marks(points, box_mask(points, low, high), origins, cells)
    chunked = box_direction_marks(
        (points[start : start + 97] for start in range(0, len(points), 97)),
        [(low, high)],
        origins,
        cells,
    )[0]
    assert MARK_PARTS < len(points) // 97, "joined several times"
    for got, expected in zip(chunked, whole, strict=True):
        assert np.array_equal(got, expected)


def test_a_crop_mask_given_its_points_direction_cells_is_the_one_computing_them() -> None:
    # the crop pass numbers each point's direction from its station once per chunk, whatever
    # the tiles it reaches; a point at its station has no direction and is never marked
    generator = np.random.default_rng(11)
    points = generator.uniform(-8.0, 8.0, size=(6000, 3)).astype(np.float32)
    origins = np.array([[0.0, 0.0, 1.5], [4.0, -3.0, 1.0]])
    points[:2] = origins.astype(np.float32)
    station = generator.integers(0, 2, size=len(points)).astype(np.int8)
    station[:2] = [0, 1]
    cells = np.array([0.04, 0.07])
    other = generator.uniform(-8.0, 8.0, size=(3000, 3)).astype(np.float32)
    low, high = np.array([-1.0, -1.5]), np.array([1.5, 2.0])
    marks = direction_marks(other, box_mask(other, low, high), origins, cells)
    numbers = own_direction_cells(points, station, origins, cells)
    assert (numbers[:2] == -1).all() and (numbers[2:] >= 0).all()
    options = {"cells": cells, "marks": marks}
    computed = crop_mask(points, station, origins, low, high, 4.0, **options)
    given = crop_mask(points, station, origins, low, high, 4.0, **options, point_cells=numbers)
    assert np.array_equal(given, computed)
    # the first station stands in the box (kept as the box's point); the second outside: no ray
    assert 0 < given.sum() < len(points) and given[0] and not given[1]
