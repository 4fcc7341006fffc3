"""Tiled comparison (issue 30): equal to the one-process comparison, across many tile borders."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.cloud import PointCloud
from app.core.datasets.lidar import LidarPair, lidar_pair
from app.core.datasets.maps import map_pair
from app.core.errors import InputError
from app.core.labels import LABEL_CHANGED
from app.core.pipeline import ComparisonResult, compare
from app.core.tiling import TileBudgetError, TilePlan, TileResult, compute_tile, merge_tiles
from app.core.tiling.compare import compare_tiled, compare_within_budget
from app.core.tiling.lean import read_pair
from app.core.tiling.plan import (
    BASELINE_BYTES,
    LOCALISATION_BYTES_PER_POINT,
    RESIDENT_BYTES_PER_POINT,
    crop_point_limit,
)
from app.core.tiling.rays import crop_masks, ray_cell_sizes
from app.core.tiling.tile import TileContext, TileSource, crop_mask
from tests.helpers.tiling import CropChecker, assert_identical_results

MIN_IOU = 0.99
BOX_TOLERANCE_M = 0.15


def _iou(first: np.ndarray, second: np.ndarray) -> float:
    union = np.count_nonzero((first == LABEL_CHANGED) | (second == LABEL_CHANGED))
    both = np.count_nonzero((first == LABEL_CHANGED) & (second == LABEL_CHANGED))
    return 1.0 if union == 0 else both / union


def _assert_same(
    one: ComparisonResult, tiled: ComparisonResult, frame_offset: np.ndarray | None = None
) -> None:
    """Labels IoU >= 0.99, the same regions (kinds, near-identical boxes), the same decision.

    ``frame_offset``: what the tiled comparison's files add to ``one``'s coordinates."""
    shift = np.zeros(3) if frame_offset is None else frame_offset
    assert tiled.localisation["tiles"]["count"] >= 3, "the scene must cross tile borders"
    for name in ("reference_label", "scan_label"):
        assert _iou(getattr(one, name), getattr(tiled, name)) >= MIN_IOU, name
    assert sorted(region.kind for region in tiled.regions) == sorted(
        region.kind for region in one.regions
    )
    # regions are listed largest first: two of near-equal size (127 and 128 points) may swap
    # places, so each is paired with the unpaired region of its kind whose box is nearest
    unpaired = list(tiled.regions)
    for expected in one.regions:
        same_kind = [region for region in unpaired if region.kind == expected.kind]
        got = min(
            same_kind,
            key=lambda region: float(
                np.abs(np.asarray(region.bbox_min) - expected.bbox_min - shift).max()
                + np.abs(np.asarray(region.bbox_max) - expected.bbox_max - shift).max()
            ),
        )
        unpaired.remove(got)
        assert np.allclose(got.bbox_min, expected.bbox_min + shift, atol=BOX_TOLERANCE_M)
        assert np.allclose(got.bbox_max, expected.bbox_max + shift, atol=BOX_TOLERANCE_M)
    assert tiled.changed == one.changed


@pytest.fixture(scope="module")
def merged_station_pair() -> tuple[LidarPair, ComparisonResult]:
    """A three-station warehouse pair and its one-process comparison (made once: the tiled and
    the lean comparisons are both checked against it)."""
    pair = lidar_pair(
        layout="warehouse", change="mixed", n_stations=3, angular_step_deg=0.8, random_state=3
    )
    one = compare(
        PointCloud.from_array(pair.reference), PointCloud.from_array(pair.scan), threads=1
    )
    return pair, one


@pytest.fixture(scope="module")
def merged_station_tiled(
    merged_station_pair: tuple[LidarPair, ComparisonResult],
) -> ComparisonResult:
    """The same pair compared in tiles in this process (the crop-file test checks against it)."""
    pair, _ = merged_station_pair
    return _tiled(PointCloud.from_array(pair.reference), PointCloud.from_array(pair.scan), 0.6)


def _tiled(
    reference: PointCloud, scan: PointCloud, crop_fraction: float, ray_reach: float = 4.0
) -> ComparisonResult:
    return compare_tiled(
        reference,
        scan,
        budget_bytes=1 << 40,
        max_crop_points=int(crop_fraction * (len(reference) + len(scan))),
        margin=1.0,
        ray_reach=ray_reach,
        threads=1,
    )


def _both(
    reference: PointCloud, scan: PointCloud, crop_fraction: float, ray_reach: float = 4.0
) -> tuple[ComparisonResult, ComparisonResult]:
    one = compare(reference, scan, threads=1)
    return one, _tiled(reference, scan, crop_fraction, ray_reach)


def test_single_station_pair_tiled_equals_one_process() -> None:
    pair = lidar_pair(layout="warehouse", change="mixed", angular_step_deg=0.8, random_state=3)
    # crops by direction are smaller: a share of 0.6 keeps the scene across 3+ tiles
    one, tiled = _both(PointCloud.from_array(pair.reference), PointCloud.from_array(pair.scan), 0.6)
    assert one.regions, "the scene has changes"
    _assert_same(one, tiled)


def test_merged_station_pair_tiled_equals_one_process(
    merged_station_pair: tuple[LidarPair, ComparisonResult], merged_station_tiled: ComparisonResult
) -> None:
    _assert_same(merged_station_pair[1], merged_station_tiled)


def test_tiles_computed_from_their_crop_files_equal_the_tiles_of_the_whole_pair(
    tmp_path,
    merged_station_pair: tuple[LidarPair, ComparisonResult],
    merged_station_tiled: ComparisonResult,
) -> None:
    """Each tile's crop written to files of its own in one pass (app.core.tiling.crops), small
    chunks cutting the clouds anywhere: the same points, order and stations as the whole pair's
    crop, so the merged comparison is identical (a moving-sensor map: make test-slow)."""
    pair, _ = merged_station_pair
    reference, scan = PointCloud.from_array(pair.reference), PointCloud.from_array(pair.scan)
    checker = CropChecker(tmp_path / "crops")
    from_files = compare_tiled(
        reference,
        scan,
        budget_bytes=1 << 40,
        max_crop_points=int(0.6 * (len(reference) + len(scan))),
        margin=1.0,
        ray_reach=4.0,
        threads=1,
        run_tiles=checker,
    )
    assert len(checker.crop_sizes) >= 2 and checker.stations_seen
    assert max(checker.crop_sizes) < 0.9 * (len(reference) + len(scan)), "no tile holds all"
    assert_identical_results(from_files, merged_station_tiled)


def test_moving_sensor_map_tiled_equals_one_process() -> None:
    pair = map_pair("robot", change="mixed", size=0.6, random_state=1)
    assert pair.reference.trajectory is not None
    one, tiled = _both(pair.reference, pair.scan, 0.55)
    _assert_same(one, tiled)


def _small_tiles() -> tuple[TilePlan, TileSource, TileContext, int]:
    pair = lidar_pair(layout="room", change="added", angular_step_deg=1.0, random_state=4)
    origins = pair.reference_origin.reshape(1, 3)
    context = TileContext(
        reference_origins=origins,
        scan_origins=pair.scan_origin.reshape(1, 3),
        reference_stations_unknown=False,
        scan_stations_unknown=False,
        min_region_points=8,
        ray_reach=2.0,
    )
    source = TileSource(reference_points=pair.reference, scan_points=pair.scan)
    from app.core.tiling.plan import plan_tiles

    total = len(pair.reference) + len(pair.scan)
    plan = plan_tiles(
        pair.reference[:, :2],
        pair.scan[:, :2],
        max_crop_points=int(0.9 * total),
        count_crop=lambda low, high: source.count_crop(low, high, 0.75, context),
        margin=0.75,
    )
    return plan, source, context, total


def test_tiles_saved_and_merged_in_any_order_give_the_same_result(tmp_path) -> None:
    plan, source, context, _ = _small_tiles()
    assert plan.n_tiles >= 2
    plan.save(tmp_path / "plan.npz")
    context.save(tmp_path / "context.npz")
    loaded_plan = TilePlan.load(tmp_path / "plan.npz")
    loaded_context = TileContext.load(tmp_path / "context.npz")
    in_memory = [compute_tile(plan, index, source, context) for index in range(plan.n_tiles)]
    for result in in_memory:
        compute_tile(loaded_plan, result.tile_index, source, loaded_context).save(
            tmp_path / f"tile{result.tile_index}.npz"
        )
    from_files = [
        TileResult.load(tmp_path / f"tile{index}.npz")
        for index in reversed(range(loaded_plan.n_tiles))
    ]
    n = (len(source.reference_points), len(source.scan_points))
    first = merge_tiles(plan, in_memory, *n, context.min_region_points)
    second = merge_tiles(loaded_plan, from_files, *n, context.min_region_points)
    assert np.array_equal(first.reference_label, second.reference_label)
    assert np.array_equal(first.scan_label, second.scan_label)
    assert np.array_equal(first.scan_region, second.scan_region)
    assert [r.n_points for r in first.regions] == [r.n_points for r in second.regions]
    with pytest.raises(InputError, match="each of the plan's"):
        merge_tiles(plan, in_memory[1:], *n, context.min_region_points)


def test_a_crop_holds_the_rays_through_its_box_within_reach() -> None:
    origins = np.zeros((1, 3))
    points = np.array([[5.0, 0.2, 0.0], [9.0, 0.4, 0.0], [20.0, 0.8, 0.0], [0.0, 5.0, 0.0]])
    low, high = np.array([2.0, -1.0]), np.array([3.0, 1.0])
    assert crop_mask(points, None, None, low, high).tolist() == [False] * 4
    reached = crop_mask(points, None, origins, low, high, ray_reach=8.0)
    assert reached.tolist() == [True, True, False, False]


def test_a_box_without_the_other_clouds_points_keeps_no_ray_crossing_it() -> None:
    # no point of the other cloud in the box: no direction marked, so only the box's own
    # points are kept (the empty marks are read, not indexed)
    origins = np.zeros((1, 3))
    points = np.array([[2.5, 0.0, 0.0], [5.0, 0.2, 0.0], [9.0, 0.4, 0.0]])
    low, high = np.array([2.0, -1.0]), np.array([3.0, 1.0])
    empty = [np.zeros(0, dtype=np.int64)]
    kept = crop_mask(points, None, origins, low, high, 8.0, cells=np.array([0.05]), marks=empty)
    assert kept.tolist() == [True, False, False]


def test_a_crop_round_a_station_keeps_the_returns_the_ray_test_reads_not_the_whole_station() -> (
    None
):
    """Every ray of a station crosses its own box in the top view; by direction, the crop keeps
    the returns within the ray test's angular reach of the other cloud's points in the box."""
    from scipy.spatial import cKDTree

    pair = lidar_pair(layout="warehouse", change="added", angular_step_deg=0.7, random_state=4)
    origins = [pair.reference_origin.reshape(1, 3), pair.scan_origin.reshape(1, 3)]
    clouds = [pair.reference, pair.scan]
    low, high = origins[1][0, :2] - 1.0, origins[1][0, :2] + 1.0  # round the scan's station
    reach, angle_factor = 8.0, 2.5
    cells = [
        ray_cell_sizes(None, len(c), o, angle_factor) for c, o in zip(clouds, origins, strict=True)
    ]
    masks = crop_masks(
        list(zip(clouds, [None, None], origins, strict=True)), cells, low, high, reach
    )
    top_view = crop_mask(pair.scan, None, origins[1], low, high, reach)
    # the ray test's view of each reference point in the box: the scan's returns within
    # angle_factor angular steps (the median distance to the second neighbour) of its direction
    offset = pair.scan - origins[1][0]
    directions = offset / np.linalg.norm(offset, axis=1, keepdims=True)
    tree = cKDTree(directions)
    step = float(np.median(tree.query(directions[::50], k=3)[0][:, 2]))
    in_box = np.all((pair.reference[:, :2] >= low) & (pair.reference[:, :2] <= high), axis=1)
    seen = pair.reference[in_box] - origins[1][0]
    needed = np.zeros(len(pair.scan), dtype=bool)
    for found in tree.query_ball_point(
        seen / np.linalg.norm(seen, axis=1, keepdims=True), angle_factor * step
    ):
        needed[found] = True
    near = np.all((pair.scan[:, :2] >= low - reach) & (pair.scan[:, :2] <= high + reach), axis=1)
    assert np.count_nonzero(needed & near) > 1000
    assert masks[1][needed & near].all(), "a return the ray test reads was dropped"
    assert top_view[masks[1]].all()  # a subset of the top view's crop
    beyond = ~np.all((pair.scan[:, :2] >= low) & (pair.scan[:, :2] <= high), axis=1)
    kept, crossing = np.count_nonzero(masks[1] & beyond), np.count_nonzero(top_view & beyond)
    assert kept < 0.25 * crossing, f"the crop keeps {kept} of the station's {crossing} rays"


def test_a_budget_too_small_for_one_tile_is_refused_with_the_budget_to_set() -> None:
    pair = lidar_pair(layout="room", change="added", angular_step_deg=1.0, random_state=4)
    reference, scan = PointCloud.from_array(pair.reference), PointCloud.from_array(pair.scan)
    total = len(reference) + len(scan)
    # room for the whole pair and 2% of it in a crop: no tile around the station is that small
    budget = BASELINE_BYTES + total * RESIDENT_BYTES_PER_POINT
    budget += total // 50 * LOCALISATION_BYTES_PER_POINT
    assert crop_point_limit(budget, total) == total // 50
    with pytest.raises(TileBudgetError, match="raise the memory budget by at least"):
        compare_within_budget(reference, scan, budget_bytes=budget, threads=1)


def _tile(index: int, core: range, members: list[int], in_core: list[bool]) -> TileResult:
    """A tile whose scan core is ``core``; its core ``members`` are changed, one region."""
    count = sum(in_core)
    changed = [point for point, kept in zip(members, in_core, strict=True) if kept]
    core_points = np.array([[float(point), 0.0, 1.0] for point in changed])
    label = np.zeros(len(core), dtype=np.int8)
    label[np.searchsorted(np.array(core), changed)] = LABEL_CHANGED
    return TileResult(
        tile_index=index,
        reference_index=np.zeros(0, dtype=np.int64),
        scan_index=np.array(core, dtype=np.int64),
        reference_label=np.zeros(0, dtype=np.int8),
        scan_label=label,
        reference_distance=np.zeros(0, dtype=np.float32),
        scan_distance=np.where(label == LABEL_CHANGED, 0.5, 0.0).astype(np.float32),
        regions={
            "cloud": np.array([1], dtype=np.int8),
            "uncertain": np.array([False]),
            "evidence": np.array([1], dtype=np.int8),
            "confidence": np.array([1.0]),
            "core_count": np.array([count]),
            "core_sum": core_points.sum(axis=0, keepdims=True),
            "core_min": core_points.min(axis=0, keepdims=True),
            "core_max": core_points.max(axis=0, keepdims=True),
            "distance_sum": np.array([0.5 * count]),
            "distance_max": np.array([0.5]),
            "member_bounds": np.array([0, len(members)]),
            "members": np.array(members, dtype=np.int64),
            "member_in_core": np.array(in_core),
        },
        figures={"localised": True, "alignment_residual": 0.0},
    )


def test_a_region_cut_by_a_border_is_joined_and_kept_whole() -> None:
    plan = TilePlan(
        lower=np.array([[-np.inf, -np.inf], [12.0, -np.inf]]),
        upper=np.array([[12.0, np.inf], [np.inf, np.inf]]),
        margin=1.0,
        crop_points=np.array([10, 10]),
        max_crop_points=10,
    )
    # scan points 10, 11 in tile 0 and 12, 13 in tile 1; each tile sees the other's
    # neighbouring point in its margin as part of its region
    results = [
        _tile(0, range(12), [10, 11, 12], [True, True, False]),
        _tile(1, range(12, 14), [11, 12, 13], [False, True, True]),
    ]
    merged = merge_tiles(plan, results, 0, 14, min_region_points=3)
    assert len(merged.regions) == 1  # each part alone (2 points) is under the minimum
    region = merged.regions[0]
    assert region.point_indices.tolist() == [10, 11, 12, 13]
    assert region.bbox_min[0] == 10.0 and region.bbox_max[0] == 13.0
    assert merged.scan_region[10:14].tolist() == [0, 0, 0, 0]
    alone = merge_tiles(
        plan,
        [
            _tile(0, range(12), [10, 11], [True, True]),
            _tile(1, range(12, 14), [12, 13], [True, True]),
        ],
        0,
        14,
        min_region_points=3,
    )
    assert alone.regions == []  # not joined: two clusters under the minimum, unchanged
    assert (alone.scan_label[10:14] == LABEL_CHANGED).sum() == 0


def test_a_georeferenced_pair_read_lean_compares_as_the_one_process(
    tmp_path, merged_station_pair: tuple[LidarPair, ComparisonResult]
) -> None:
    """Read as float32 near an offset (the CLI's read_pair when the headers say the pair will be
    tiled): the same labels, decision and regions (in the files' frame) as the one-process
    comparison of the pair, float64 and whole."""
    pair, one = merged_station_pair
    georeference = np.array([512_345.0, 4_203_210.0, 87.0])  # UTM-like: float32 alone fails
    paths = {"reference": tmp_path / "reference.npy", "scan": tmp_path / "scan.npy"}
    np.save(paths["reference"], pair.reference + georeference)
    np.save(paths["scan"], pair.scan + georeference)
    total = len(pair.reference) + len(pair.scan)
    budget = BASELINE_BYTES + total * LOCALISATION_BYTES_PER_POINT // 2  # half a crop: tiled

    def read(side: str) -> PointCloud:
        return PointCloud.from_array(np.load(paths[side]))

    reference, scan, offset = read_pair(paths["reference"], paths["scan"], read, budget)
    assert offset is not None and np.linalg.norm(offset - georeference) < 100.0
    assert reference.points.dtype == scan.points.dtype == np.float32
    lean = compare_within_budget(
        reference,
        scan,
        budget_bytes=budget,
        frame_offset=offset,
        max_crop_points=int(0.6 * total),
        margin=1.0,
        ray_reach=4.0,
        threads=1,
    )
    _assert_same(one, lean, frame_offset=georeference)
    assert lean.reference_label.shape == (len(pair.reference),)
    unfit = read_pair(paths["reference"], paths["scan"], read, budget * 100)
    assert unfit[2] is None and unfit[0].points.dtype == np.float64
