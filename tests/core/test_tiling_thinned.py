"""Thinned tiles (issue 30): a near field too dense for the budget even at the smallest tile is
localised on one point a cube and its labels carried back to every point."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from app.core.cloud import PointCloud
from app.core.labels import LABEL_CHANGED
from app.core.pipeline import ComparisonResult, compare
from app.core.tiling import TileBudgetError
from app.core.tiling.compare import compare_tiled
from app.core.tiling.plan import (
    BASELINE_BYTES,
    LOCALISATION_BYTES_PER_POINT,
    RESIDENT_BYTES_PER_POINT,
)
from app.core.tiling.thinning import (
    MAX_THINNING_CELL_METRES,
    MIN_THINNING_CELL_METRES,
    representatives,
)
from app.testing.files import ply_bytes

BOX_LOW = np.array([0.1, 0.1, 0.0])
BOX_SIDE = 0.3


def _floor_with_a_dense_disc(rng: np.random.Generator, box: bool) -> np.ndarray:
    """A 4 x 4 m floor, sparse (4k points) but for a 0.7 m disc of 20k points round the origin
    (a station's near field, about 9 mm apart), plus, with ``box``, a 0.3 m box on the disc
    (five faces, 3k points); 2 mm of noise."""
    far = np.column_stack([rng.uniform(-2, 2, (4000, 2)), np.zeros(4000)])
    radius, angle = 0.7 * np.sqrt(rng.uniform(0, 1, 20_000)), rng.uniform(0, 2 * np.pi, 20_000)
    parts = [far, np.column_stack([radius * np.cos(angle), radius * np.sin(angle), 0 * radius])]
    if box:
        face, (u, v) = rng.integers(0, 5, 3000), rng.uniform(0, BOX_SIDE, (2, 3000))
        side = np.where(face % 2 == 0, 0.0, BOX_SIDE)
        walls = [
            np.column_stack([u, v, np.full(3000, BOX_SIDE)]),  # the lid
            np.column_stack([u, side, v]),
            np.column_stack([side, u, v]),
        ]
        parts.append(np.choose((np.minimum(face, 2))[:, None], walls) + BOX_LOW)
    points = np.concatenate(parts)
    return points + rng.normal(0, 0.002, points.shape)


@pytest.fixture(scope="module")
def dense_pair() -> tuple[PointCloud, PointCloud, ComparisonResult]:
    """The pair (the scan adds the box) and its one-process comparison."""
    rng = np.random.default_rng(7)
    reference = PointCloud.from_array(_floor_with_a_dense_disc(rng, box=False))
    scan = PointCloud.from_array(_floor_with_a_dense_disc(rng, box=True))
    return reference, scan, compare(reference, scan, threads=1)


def _budget(reference: PointCloud, scan: PointCloud, crop_share: float) -> int:
    """A budget holding the whole pair and crops of ``crop_share`` of its points."""
    total = len(reference) + len(scan)
    crop = int(crop_share * total) * LOCALISATION_BYTES_PER_POINT
    return BASELINE_BYTES + total * RESIDENT_BYTES_PER_POINT + crop


def _iou(first: np.ndarray, second: np.ndarray) -> float:
    union = np.count_nonzero((first == LABEL_CHANGED) | (second == LABEL_CHANGED))
    return np.count_nonzero((first == LABEL_CHANGED) & (second == LABEL_CHANGED)) / max(1, union)


def test_a_dense_near_field_is_thinned_finds_the_same_change_and_labels_every_point(
    dense_pair: tuple[PointCloud, PointCloud, ComparisonResult],
) -> None:
    reference, scan, one = dense_pair
    tiled = compare_tiled(
        reference, scan, budget_bytes=_budget(reference, scan, 0.6), margin=0.5, threads=1
    )
    tiles = tiled.localisation["tiles"]
    assert tiles["thinned_tiles"], "the disc's tiles are over the budget"
    assert len(tiles["thinned_tiles"]) < tiles["count"], "only the tiles over the limit"
    for figures in tiles["per_tile"]:
        crop = figures["crop_reference_points"] + figures["crop_scan_points"]
        if figures["tile"] in tiles["thinned_tiles"]:
            assert MIN_THINNING_CELL_METRES <= figures["thinning_cell_m"]
            assert figures["thinning_cell_m"] <= MAX_THINNING_CELL_METRES
            thinned = figures["thinned_reference_points"] + figures["thinned_scan_points"]
            assert thinned <= tiles["max_crop_points"] < crop
        else:
            assert "thinning_cell_m" not in figures
    assert _iou(one.scan_label, tiled.scan_label) >= 0.9
    assert np.count_nonzero(tiled.reference_label == LABEL_CHANGED) == 0
    assert [region.kind for region in tiled.regions] == ["added"]
    region = tiled.regions[0]
    assert np.allclose(region.bbox_min, one.regions[0].bbox_min, atol=0.05)
    assert np.allclose(region.bbox_max, one.regions[0].bbox_max, atol=0.05)
    assert np.allclose(region.bbox_max[:2], BOX_LOW[:2] + BOX_SIDE, atol=0.05)
    # every point labelled; the region counts the original points, not the thinned ones
    assert len(tiled.scan_label) == len(scan) and len(tiled.reference_label) == len(reference)
    for result in (one, tiled):
        assert np.count_nonzero(result.scan_label == -1) <= 0.001 * len(scan)
    assert region.n_points == np.count_nonzero(tiled.scan_label == LABEL_CHANGED)
    assert region.n_points >= 0.9 * one.regions[0].n_points


def test_a_budget_too_small_even_thinned_is_refused_with_the_budget_to_set(
    dense_pair: tuple[PointCloud, PointCloud, ComparisonResult],
) -> None:
    reference, scan, _ = dense_pair
    # the planner: the crop cannot even be held beside a thinned copy
    with pytest.raises(TileBudgetError, match=r"set it to at least [\d,]+ MiB"):
        compare_tiled(
            reference, scan, budget_bytes=_budget(reference, scan, 0.2), margin=0.5, threads=1
        )
    # the tile: held, but still over its limit at the coarsest cell
    with pytest.raises(TileBudgetError, match=r"raise the memory budget by at least [\d,]+ MiB"):
        compare_tiled(
            reference, scan, budget_bytes=_budget(reference, scan, 0.4), margin=0.5, threads=1
        )


def test_each_point_is_represented_by_the_first_point_of_its_cube() -> None:
    rng = np.random.default_rng(1)
    points = rng.uniform(0, 0.1, (5000, 3))
    cell = 0.02
    kept, representative = representatives(points, cell)
    assert np.all(np.diff(kept) > 0)
    cubes = np.floor((points - points.min(axis=0)) / cell).astype(int)
    assert len(np.unique(cubes, axis=0)) == len(kept)
    assert np.array_equal(cubes[kept[representative]], cubes)  # the same cube
    assert np.all(kept[representative] <= np.arange(len(points)))  # its first point
    assert np.array_equal(representative[kept], np.arange(len(kept)))  # a kept point: itself
    lone = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    assert representatives(lone, cell)[0].tolist() == [0, 1]


def test_a_streamed_tile_whose_written_crop_is_over_the_limit_runs_thinned(
    dense_pair: tuple[PointCloud, PointCloud, ComparisonResult], tmp_path, monkeypatch
) -> None:
    # the plan counts crops on a sample and can count a tile low: here it counts every tile
    # within the limit (none thinned); the crops as written are what the tiles hold, so a
    # tile whose written crop is over the limit must still run thinned
    from app.core.tiling import plan as plan_module
    from app.core.tiling import streamed

    reference, scan, one = dense_pair
    paths = [tmp_path / "reference.ply", tmp_path / "scan.ply"]
    for path, cloud in zip(paths, (reference, scan), strict=True):
        path.write_bytes(ply_bytes(cloud.points))
    limit = int(0.6 * (len(reference) + len(scan)))

    def under_counted(*args, **kwargs) -> plan_module.TilePlan:
        plan = plan_module.plan_tiles(*args, **kwargs)
        return dataclasses.replace(
            plan, crop_points=np.minimum(plan.crop_points, limit), thinning_cells=None
        )

    monkeypatch.setattr(streamed, "plan_tiles", under_counted)
    result = streamed.compare_streamed(
        *paths, work_dir=tmp_path / "work", budget_bytes=1 << 40, max_crop_points=limit,
        margin=0.5, threads=1,
    )  # fmt: skip
    tiles = result.localisation["tiles"]
    over = [
        figures
        for figures in tiles["per_tile"]
        if figures["crop_reference_points"] + figures["crop_scan_points"] > limit
    ]
    assert over, "a crop as written is over the limit"
    for figures in over:
        assert figures["tile"] in tiles["thinned_tiles"]
        assert MIN_THINNING_CELL_METRES <= figures["thinning_cell_m"] <= MAX_THINNING_CELL_METRES
        assert figures["thinned_reference_points"] + figures["thinned_scan_points"] <= limit
    assert len(over) < tiles["count"], "the tiles within the limit run whole"
    for figures in tiles["per_tile"]:
        if figures not in over:
            assert "thinning_cell_m" not in figures
    assert [region.kind for region in result.regions] == ["added"]
    assert _iou(one.scan_label, np.asarray(result.scan_label)) >= 0.9
