"""Each tile's crop written to files of its own in one pass (app.core.tiling.crops).

A tile computed from its crop files must equal the tile computed from the whole pair: the same
points in the same order, the same stations and rays, so the merged comparison is identical.
Small chunks make the pass cut the clouds at many places.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from app.core.cloud import PointCloud
from app.core.datasets.lidar import lidar_pair
from app.core.datasets.maps import map_pair
from app.core.pipeline import ComparisonResult
from app.core.tiling import TileContext, TilePlan, TileResult, TileSource, compute_tile
from app.core.tiling.compare import compare_tiled
from app.core.tiling.crops import TileCropFiles, crop_file, write_tile_crops

CHUNK = 997
"""Points a step of the pass: a prime, so chunk borders fall anywhere in the crops."""


class CropChecker:
    """A tile runner that writes the crops, checks each against the whole pair's crop and
    computes the tiles from the crop files only."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        self.crop_sizes: list[int] = []
        self.stations_seen = False
        self.rays_seen = False

    def __call__(
        self, plan: TilePlan, source: TileSource, context: TileContext, threads: int, report
    ) -> list[TileResult]:
        self.crop_sizes = write_tile_crops(
            self.directory, plan, source, context, chunk_points=CHUNK
        )
        crops = TileCropFiles(self.directory)
        for tile_index in range(plan.n_tiles):
            whole, alone = (
                source.crop(plan, tile_index, context),
                crops.crop(plan, tile_index, context),
            )
            assert self.crop_sizes[tile_index] == len(whole.reference_index) + len(whole.scan_index)
            for name in ("reference", "scan"):
                size = crop_file(self.directory, tile_index, name).stat().st_size
                records = len(getattr(whole, f"{name}_index"))
                assert size <= records * 36  # its crop only: 3 float64, index, station
                assert np.array_equal(
                    getattr(alone, f"{name}_index"), getattr(whole, f"{name}_index")
                )
                points = getattr(alone, f"{name}_points")
                assert points.dtype == np.float64
                assert np.array_equal(points, getattr(whole, f"{name}_points"))
                station = getattr(whole, f"{name}_station")
                if station is None:
                    assert getattr(alone, f"{name}_station") is None
                else:
                    self.stations_seen = True
                    assert np.array_equal(getattr(alone, f"{name}_station"), station)
                rays = getattr(whole, f"{name}_rays")
                if rays is None:
                    assert getattr(alone, f"{name}_rays") is None
                else:
                    self.rays_seen = True
                    for got, expected in zip(getattr(alone, f"{name}_rays"), rays, strict=True):
                        assert np.array_equal(got, expected)
        return [
            compute_tile(plan, tile_index, crops, context, threads=threads)
            for tile_index in range(plan.n_tiles)
        ]


def _tiled(reference: PointCloud, scan: PointCloud, crop_share: float, **options):
    return compare_tiled(
        reference,
        scan,
        budget_bytes=1 << 40,
        max_crop_points=int(crop_share * (len(reference) + len(scan))),
        margin=1.0,
        ray_reach=4.0,
        threads=1,
        **options,
    )


def _assert_identical(first: ComparisonResult, second: ComparisonResult) -> None:
    for name in ("label", "region"):
        for side in ("reference", "scan"):
            key = f"{side}_{name}"
            assert np.array_equal(getattr(first, key), getattr(second, key)), key
    for side in ("reference", "scan"):
        key = f"{side}_distance"
        assert np.array_equal(getattr(first, key), getattr(second, key), equal_nan=True), key
    assert first.regions == second.regions
    assert (first.score, first.changed) == (second.score, second.changed)


@pytest.mark.parametrize(
    "kind",
    ["stations", pytest.param("trajectory", marks=pytest.mark.slow)],  # make test keeps one
)
def test_a_tiled_comparison_from_crop_files_equals_the_whole_pairs(kind, tmp_path) -> None:
    if kind == "stations":
        pair = lidar_pair(
            layout="warehouse", change="mixed", n_stations=3, angular_step_deg=0.8, random_state=3
        )
        reference, scan = PointCloud.from_array(pair.reference), PointCloud.from_array(pair.scan)
        share = 0.6
    else:
        pair = map_pair("robot", change="mixed", size=0.6, random_state=1)
        reference, scan, share = pair.reference, pair.scan, 0.55
    checker = CropChecker(tmp_path / "crops")
    from_files = _tiled(reference, scan, share, run_tiles=checker)
    in_process = _tiled(reference, scan, share)
    assert len(checker.crop_sizes) >= 2, "several tiles"
    assert checker.stations_seen if kind == "stations" else checker.rays_seen
    assert in_process.regions, "the scene has changes"
    assert max(checker.crop_sizes) < 0.9 * (len(reference) + len(scan)), "no tile holds all"
    _assert_identical(from_files, in_process)
