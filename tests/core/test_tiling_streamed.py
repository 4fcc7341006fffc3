"""The streamed tiled comparison (app.core.tiling.streamed): files read in chunks, the stages
on subsamples, each tile's input in its own files, the labels merged into files.

On pairs no larger than the subsample the result must be the lean tiled comparison's (what
``scandiff compare`` runs on a pair over the budget) point for point: labels, distances,
region numbers, regions, score and decision.  Small tiles are forced (``max_crop_points``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from app.core.cloud import PointCloud, choose_local_origin
from app.core.datasets.lidar import lidar_pair, steps_for_points
from app.core.formats import read_point_cloud
from app.core.labels import LABEL_CHANGED
from app.core.origins.sampling import lidar_sampling
from app.core.origins.station_recovery import measured_sampling
from app.core.pipeline import ComparisonResult
from app.core.tiling.compare import compare_tiled
from app.core.tiling.lean import float32_cloud
from app.core.tiling.pair_files import (
    streamed_outputs,
    survey,
    write_details_npz,
    write_labels_npz,
)
from app.core.tiling.streamed import compare_streamed
from app.testing.files import ply_bytes

OPTIONS = {"budget_bytes": 1 << 40, "margin": 1.0, "ray_reach": 4.0, "threads": 1}


def _write_pair(tmp_path: Path, n_stations: int, random_state: int, shift: float = 0.0):
    pair = lidar_pair(
        layout="warehouse",
        change="mixed",
        n_stations=n_stations,
        angular_step_deg=0.8,
        random_state=random_state,
    )
    paths = []
    for name, points in (("reference", pair.reference), ("scan", pair.scan)):
        path = tmp_path / f"{name}.ply"
        path.write_bytes(ply_bytes(points + shift))
        paths.append(path)
    return paths


def _lean_tiled(paths: list[Path], crop_points: int, **options) -> ComparisonResult:
    """What the CLI runs on a pair over its budget: both read lean, then compare_tiled."""
    reference = read_point_cloud(paths[0])
    offset = choose_local_origin(reference.points)
    clouds = [float32_cloud(reference, offset), float32_cloud(read_point_cloud(paths[1]), offset)]
    return compare_tiled(
        *clouds, max_crop_points=crop_points, frame_offset=offset, **OPTIONS, **options
    )


def _assert_identical(streamed: ComparisonResult, tiled: ComparisonResult) -> None:
    for name in ("label", "region", "distance"):
        for side in ("reference", "scan"):
            key = f"{side}_{name}"
            assert np.array_equal(
                np.asarray(getattr(streamed, key)), getattr(tiled, key), equal_nan=True
            ), key
    assert streamed.regions == tiled.regions
    assert streamed.uncertain_regions == tiled.uncertain_regions
    assert (streamed.score, streamed.threshold, streamed.changed) == (
        tiled.score,
        tiled.threshold,
        tiled.changed,
    )
    assert (streamed.n_reference, streamed.n_scan) == (tiled.n_reference, tiled.n_scan)
    assert streamed.localisation["tiles"] == tiled.localisation["tiles"]


def _crop_sizes(result: ComparisonResult) -> list[int]:
    """Points of both clouds in each tile's crop."""
    return [
        tile["crop_reference_points"] + tile["crop_scan_points"]
        for tile in result.localisation["tiles"]["per_tile"]
    ]


@pytest.mark.parametrize(
    ("n_stations", "random_state", "shift", "ray_directions"),
    [(3, 3, 0.0, True), (3, 3, 0.0, False), (1, 5, 452_000.0, True)],
)
def test_a_streamed_comparison_equals_the_lean_tiled_one(
    tmp_path, n_stations, random_state, shift, ray_directions
) -> None:
    paths = _write_pair(tmp_path, n_stations, random_state, shift)
    n_points = sum(len(read_point_cloud(path)) for path in paths)
    crop_points = int(0.6 * n_points)
    tiled = _lean_tiled(paths, crop_points, ray_directions=ray_directions)
    assert tiled.localisation["tiles"]["count"] >= 3, "the scene crosses tile borders"
    assert tiled.regions, "the scene has changes"
    crop_sizes = _crop_sizes(tiled)
    streamed = compare_streamed(
        *paths,
        work_dir=tmp_path / "work",
        max_crop_points=crop_points,
        ray_directions=ray_directions,
        **OPTIONS,
    )
    _assert_identical(streamed, tiled)  # the same plan, crops and labels, directions or not
    if n_stations > 1 and ray_directions:  # the filter keeps fewer of the other's returns
        top_view = _lean_tiled(paths, crop_points, ray_directions=False)
        assert sum(crop_sizes) < sum(_crop_sizes(top_view))
    assert isinstance(streamed.reference_label, np.memmap), "the labels stay on disk"
    outputs = streamed_outputs(streamed)
    assert outputs is not None and streamed_outputs(tiled) is None
    write_labels_npz(tmp_path / "streamed.npz", outputs, chunk_points=4093)
    write_details_npz(tmp_path / "details.npz", outputs, chunk_points=4093)
    tiled.write_labels_npz(tmp_path / "tiled.npz")
    with np.load(tmp_path / "streamed.npz") as ours, np.load(tmp_path / "tiled.npz") as theirs:
        assert sorted(ours.files) == sorted(theirs.files)
        for name in theirs.files:
            assert ours[name].dtype == theirs[name].dtype, name
            assert np.array_equal(ours[name], theirs[name]), name
    with np.load(tmp_path / "details.npz") as details:
        for name in ("reference_distance", "scan_distance", "reference_region", "scan_region"):
            assert np.array_equal(details[name], getattr(tiled, name), equal_nan=True), name


def test_a_streamed_comparison_on_subsamples_finds_the_same_changes(tmp_path) -> None:
    """Clouds larger than the subsample: the stages see a third of each, the tiles all of it."""
    paths = _write_pair(tmp_path, 3, 3)
    n_points = sum(len(read_point_cloud(path)) for path in paths)
    crop_points = int(0.6 * n_points)
    tiled = _lean_tiled(paths, crop_points)
    streamed = compare_streamed(
        *paths,
        work_dir=tmp_path / "work",
        max_crop_points=crop_points,
        subsample_points=n_points // 6,
        **OPTIONS,
    )
    for side in ("reference", "scan"):
        ours = np.asarray(getattr(streamed, f"{side}_label")) == LABEL_CHANGED
        theirs = getattr(tiled, f"{side}_label") == LABEL_CHANGED
        union = np.count_nonzero(ours | theirs)
        assert union == 0 or np.count_nonzero(ours & theirs) / union >= 0.95, side
    assert [region.kind for region in streamed.regions] == [region.kind for region in tiled.regions]
    assert streamed.changed == tiled.changed


def test_non_finite_rows_keep_their_place_unobserved(tmp_path) -> None:
    paths = _write_pair(tmp_path, 3, 3)
    reference = read_point_cloud(paths[0]).points.copy()
    holes = np.arange(5, len(reference), 997)
    reference[holes] = np.nan
    paths[0].write_bytes(ply_bytes(reference))
    n_points = len(reference) - len(holes) + len(read_point_cloud(paths[1]))
    crop_points = int(0.6 * n_points)
    tiled = _lean_tiled(paths, crop_points)
    streamed = compare_streamed(
        *paths, work_dir=tmp_path / "work", max_crop_points=crop_points, **OPTIONS
    )
    assert len(streamed.reference_label) == len(reference)
    assert np.all(np.asarray(streamed.reference_label)[holes] == -1)
    _assert_identical(streamed, tiled)


def test_the_stages_see_only_the_subsample(tmp_path) -> None:
    paths = _write_pair(tmp_path, 3, 3)
    seen: list[int] = []

    def progress(stage: str, fraction: float) -> None:
        del stage, fraction

    from app.core.tiling import streamed as module

    original = module.load_pair

    def spy(reference: PointCloud, scan: PointCloud, **options):
        seen.extend([len(reference), len(scan)])
        return original(reference, scan, **options)

    module.load_pair = spy  # type: ignore[assignment]
    try:
        n_points = len(read_point_cloud(paths[0]))
        compare_streamed(
            *paths,
            work_dir=tmp_path / "work",
            max_crop_points=int(1.2 * n_points),
            subsample_points=n_points // 10,
            progress=progress,
            **OPTIONS,
        )
    finally:
        module.load_pair = original  # type: ignore[assignment]
    assert seen[0] <= n_points // 10 + 1


def test_a_subsampled_file_is_lidar_tested_on_whole_voxels_at_full_density(tmp_path) -> None:
    # an even subsample of a shuffled file thins every ring at random: its twins are gone
    # (the 20M pair's 2M-point subsample was judged not lidar-like, issue 30)
    survey_pair = lidar_pair(
        layout="room",
        change="none",
        n_stations=3,
        angular_step_deg=steps_for_points(120_000, 3),
        range_noise=0.08,
        random_state=3,
    )
    path = tmp_path / "reference.ply"
    path.write_bytes(ply_bytes(survey_pair.reference))
    cloud, subsample, voxels = survey(path, None, len(survey_pair.reference) // 4)
    assert cloud.step == 4 and voxels is not None
    assert not lidar_sampling(subsample).lidar_like
    assert lidar_sampling(survey_pair.reference).lidar_like
    whole = PointCloud(subsample, None, len(subsample), sampling_points=voxels)  # type: ignore[arg-type]
    assert measured_sampling(subsample, whole, 0).lidar_like
    assert survey(path, None, len(survey_pair.reference))[2] is None  # no subsample, no voxels
