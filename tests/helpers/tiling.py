"""A tile runner that checks each tile's crop files against the whole pair's crop (issue 30:
tiles computed from their own files must equal tiles computed from the whole pair)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from app.core.pipeline import ComparisonResult
from app.core.tiling import TileContext, TilePlan, TileResult, TileSource, compute_tile
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


def assert_identical_results(first: ComparisonResult, second: ComparisonResult) -> None:
    """Two tiled comparisons agree point for point: labels, region numbers, distances, regions,
    score, threshold, decision, sizes and tiles (labels may be memory-mapped files)."""
    for name in ("label", "region", "distance"):
        for side in ("reference", "scan"):
            key = f"{side}_{name}"
            assert np.array_equal(
                np.asarray(getattr(first, key)), getattr(second, key), equal_nan=True
            ), key
    assert first.regions == second.regions
    assert first.uncertain_regions == second.uncertain_regions
    assert (first.score, first.threshold, first.changed) == (
        second.score,
        second.threshold,
        second.changed,
    )
    assert (first.n_reference, first.n_scan) == (second.n_reference, second.n_scan)
    assert first.localisation["tiles"] == second.localisation["tiles"]
