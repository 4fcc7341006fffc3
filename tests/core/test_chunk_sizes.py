"""The chunked passes over a cloud keep each step's temporaries under the mmap threshold.

``app.kit.allocator`` fixes glibc's mmap threshold at 1 MiB for the command line and the
workers: a larger block is a fresh mapping whose pages fault in (and are zeroed) on first
touch, every step again, while a smaller one reuses the heap's pages.  At 1M + 1M points the
surface levels' 2,048-point steps (4.7 MB gathers of 96 neighbours) faulted ~90k pages in,
the Z-order's 65,536-point chunks ~17k, the origins' Hough votes of 4,000 lines (9 MB arrays)
and whole-cloud voxel hashes most of the rest: over a third of the comparison's page faults.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.core.detectors.base import KEY_BLOCK_ROWS, point_keys
from app.core.detectors.voxel_grid import VOXEL_BLOCK_ROWS
from app.core.localise.settings import CHUNK, GATHER_CHUNK, QUERY_CHUNK
from app.core.localise.surface_levels import LEVEL_CHUNK, LEVEL_NEIGHBOURS
from app.core.origins.columns import HOUGH_CELLS, HOUGH_CHUNK_LINES
from app.core.origins.voxels import HASH_BLOCK_ROWS
from app.core.spatial_order import ORDER_CHUNK
from app.kit.allocator import MMAP_THRESHOLD_BYTES

FLOAT64 = 8
HOUGH_STEPS = math.ceil(2 * math.sqrt(2) * HOUGH_CELLS)
"""Steps along a Hough line: twice the accumulator's diagonal over its cell size."""


@pytest.mark.parametrize(
    ("step", "bytes_per_row"),
    [
        ("surface levels: (chunk, 96, 3) gathers", LEVEL_CHUNK * LEVEL_NEIGHBOURS * 3 * FLOAT64),
        ("Z-order: (chunk, 3) coordinates", ORDER_CHUNK * 3 * FLOAT64),
        ("detector voxels: (chunk, 3) coordinates", VOXEL_BLOCK_ROWS * 3 * FLOAT64),
        ("detector keys: (chunk,) words", KEY_BLOCK_ROWS * FLOAT64),
        ("origins' voxel hash: (chunk,) words", HASH_BLOCK_ROWS * FLOAT64),
        ("Hough votes: (lines, steps) floats", HOUGH_CHUNK_LINES * HOUGH_STEPS * FLOAT64),
        ("gathers of 11 neighbours: (chunk, 11, 3)", GATHER_CHUNK * 11 * 3 * FLOAT64),
        ("k-NN queries: (chunk, 11) distances", QUERY_CHUNK * 11 * FLOAT64),
        ("per-point work: (chunk, 11) gathers", CHUNK * 11 * FLOAT64),
    ],
)
def test_a_chunk_temporary_stays_under_the_mmap_threshold(step: str, bytes_per_row: int) -> None:
    assert bytes_per_row < MMAP_THRESHOLD_BYTES, step


def test_the_point_keys_do_not_depend_on_the_blocks(monkeypatch: pytest.MonkeyPatch) -> None:
    """Keys mixed a block at a time, in place, are the keys of the whole cloud at once."""
    import app.core.detectors.base as base

    points = np.random.default_rng(4).normal(size=(10_001, 3)) * 30.0
    whole = point_keys(points, seed=9)
    monkeypatch.setattr(base, "KEY_BLOCK_ROWS", 1_000)
    assert np.array_equal(point_keys(points, seed=9), whole)
    assert np.array_equal(point_keys(points[:1], seed=9), whole[:1])
    assert point_keys(points[:0], seed=9).shape == (0,)
