"""Each tile's crop written to files of its own in one pass (app.core.tiling.crops), for a
moving-sensor map (rays from a trajectory).

A tile computed from its crop files must equal the tile computed from the whole pair: the same
points in the same order, the same stations and rays, so the merged comparison is identical.
Small chunks make the pass cut the clouds at many places.  make test runs the merged-station
case (tests/core/test_tiling.py, on its module's pair); this one is in make test-slow.
"""

from __future__ import annotations

import pytest

from app.core.datasets.maps import map_pair
from app.core.tiling.compare import compare_tiled
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
