"""The streamed tiled comparison (app.core.tiling.streamed): files read in chunks, the stages
on subsamples, each tile's input in its own files, the labels merged into files.

On pairs no larger than the subsample the result must be the lean tiled comparison's (what
``scandiff compare`` runs on a pair over the budget) point for point: labels, distances,
region numbers, regions, score and decision.  Small tiles are forced (``max_crop_points``).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from app.core.cloud import PointCloud, choose_local_origin
from app.core.datasets.lidar import lidar_pair, steps_for_points
from app.core.datasets.lidar_files import write_lidar_pair
from app.core.formats import read_point_cloud
from app.core.labels import LABEL_CHANGED
from app.core.origins.own_frame import resolve_moved_cloud
from app.core.origins.sampling import lidar_sampling
from app.core.origins.station_recovery import (
    measured_sampling,
    recover_stations,
    resolve_stations,
)
from app.core.pipeline import ComparisonResult
from app.core.registration import apply_transform
from app.core.tiling.compare import compare_tiled
from app.core.tiling.disk import DiskSpaceError
from app.core.tiling.lean import float32_cloud
from app.core.tiling.pair_files import (
    streamed_outputs,
    survey,
    write_details_npz,
    write_labels_npz,
)
from app.core.tiling.streamed import compare_streamed
from app.testing.files import ply_bytes
from tests.helpers.tiling import assert_identical_results

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


def _crop_sizes(result: ComparisonResult) -> list[int]:
    """Points of both clouds in each tile's crop."""
    return [
        tile["crop_reference_points"] + tile["crop_scan_points"]
        for tile in result.localisation["tiles"]["per_tile"]
    ]


@pytest.fixture(scope="module")
def three_station_pair(tmp_path_factory) -> tuple[list[Path], int, ComparisonResult]:
    """The three-station warehouse pair's files, its size and its lean tiled comparison (made
    once: three tests compare the streamed path against it)."""
    paths = _write_pair(tmp_path_factory.mktemp("three-stations"), 3, 3)
    n_points = sum(len(read_point_cloud(path)) for path in paths)
    return paths, n_points, _lean_tiled(paths, int(0.6 * n_points))


def _assert_streamed_equals_lean(
    paths: list[Path], work_dir: Path, n_points: int, tiled: ComparisonResult, **options
) -> ComparisonResult:
    """Stream the pair with the lean run's tiles and check the result and its files equal it
    (the crops by direction too unless ``ray_directions=False``, as the lean run's)."""
    crop_points = int(0.6 * n_points)
    assert tiled.localisation["tiles"]["count"] >= 3, "the scene crosses tile borders"
    assert tiled.regions, "the scene has changes"
    streamed = compare_streamed(
        *paths, work_dir=work_dir / "work", max_crop_points=crop_points, **OPTIONS, **options
    )
    assert_identical_results(streamed, tiled)
    assert isinstance(streamed.reference_label, np.memmap), "the labels stay on disk"
    outputs = streamed_outputs(streamed)
    assert outputs is not None and streamed_outputs(tiled) is None
    write_labels_npz(work_dir / "streamed.npz", outputs, chunk_points=4093)
    write_details_npz(work_dir / "details.npz", outputs, chunk_points=4093)
    tiled.write_labels_npz(work_dir / "tiled.npz")
    with np.load(work_dir / "streamed.npz") as ours, np.load(work_dir / "tiled.npz") as theirs:
        assert sorted(ours.files) == sorted(theirs.files)
        for name in theirs.files:
            assert ours[name].dtype == theirs[name].dtype, name
            assert np.array_equal(ours[name], theirs[name]), name
    with np.load(work_dir / "details.npz") as details:
        for name in ("reference_distance", "scan_distance", "reference_region", "scan_region"):
            assert np.array_equal(details[name], getattr(tiled, name), equal_nan=True), name
    return streamed


def test_a_streamed_comparison_equals_the_lean_tiled_one(tmp_path, three_station_pair) -> None:
    # by default the crops keep the other sensor's returns by direction too, both paths
    paths, n_points, tiled = three_station_pair
    _assert_streamed_equals_lean(paths, tmp_path, n_points, tiled)


def test_the_crops_on_disk_hold_exactly_the_points_the_tiles_read(
    tmp_path, three_station_pair
) -> None:
    # each cloud's pass reads the other cloud's file for its tiles' direction marks and writes
    # only the returns the tiles read, in packed records (float32 point, uint32 index, int8
    # station): the crops' bytes are what the tiles' crop sizes say, no more
    from app.core.tiling import crops

    paths, n_points, tiled = three_station_pair
    streamed = _assert_streamed_equals_lean(paths, tmp_path, n_points, tiled)
    layout = json.loads((tmp_path / "work" / "crops" / "crops.json").read_text())
    assert not any(layout[side]["directions"] for side in ("reference", "scan"))
    record = crops.record_dtype(np.zeros((0, 3), np.float32), n_points, 3)
    assert record.itemsize == 17
    written = sum(path.stat().st_size for path in (tmp_path / "work" / "crops").glob("*.bin"))
    assert written == record.itemsize * sum(_crop_sizes(streamed))


def test_tiles_marking_their_directions_in_small_reads_equal_the_lean_one(
    tmp_path, three_station_pair, monkeypatch
) -> None:
    # passes that do not read the other cloud (an earlier attempt's) write the crops in the
    # top view only; each tile marks its directions from the other cloud's points in its box
    # and filters its crop as it reads it, here a few hundred records at a time: the crops,
    # and so the result, are the lean run's
    from app.core.tiling import crop_passes, crops

    monkeypatch.setattr(crops, "READ_CHUNK", 997)
    monkeypatch.setattr(crop_passes.CropPass, "filters_by_direction", lambda *_: False)
    paths, n_points, tiled = three_station_pair
    streamed = _assert_streamed_equals_lean(paths, tmp_path, n_points, tiled)
    layout = json.loads((tmp_path / "work" / "crops" / "crops.json").read_text())
    assert all(layout[side]["directions"] for side in ("reference", "scan"))
    written = sum(path.stat().st_size for path in (tmp_path / "work" / "crops").glob("*.bin"))
    record_bytes = crops.record_dtype(np.zeros((0, 3), np.float32), n_points, 3).itemsize
    assert written > record_bytes * sum(_crop_sizes(streamed)), "filtered by the tiles"


def test_a_pair_whose_crops_do_not_fit_the_disk_is_refused_before_a_crop_is_written(
    tmp_path, three_station_pair
) -> None:
    paths, n_points, _ = three_station_pair
    seen: list[Path] = []

    def free_disk(directory: Path) -> int:  # a disk with 1 MB free
        seen.append(directory)
        return 1_000_000

    with pytest.raises(DiskSpaceError) as refusal:
        compare_streamed(
            *paths,
            work_dir=tmp_path / "work",
            max_crop_points=int(0.6 * n_points),
            free_disk=free_disk,
            keep_free_disk_bytes=500_000,
            **OPTIONS,
        )
    message = str(refusal.value)
    assert "need about" in message and "only 0.0 GB are free" in message, message
    assert "0.0 GB must stay free" in message and str(tmp_path / "work") in message
    assert seen == [tmp_path / "work"]
    assert not (tmp_path / "work" / "crops").exists()
    assert not list((tmp_path / "work").glob("crops*/*.bin")), "no crop written"


@pytest.mark.slow  # a second streamed run of the module pair (~10 CPU s): make test-slow
def test_without_the_direction_filter_too_and_its_crops_are_larger(
    tmp_path, three_station_pair
) -> None:
    paths, n_points, by_direction = three_station_pair
    top_view = _lean_tiled(paths, int(0.6 * n_points), ray_directions=False)
    _assert_streamed_equals_lean(paths, tmp_path, n_points, top_view, ray_directions=False)
    # the filter keeps fewer of the other sensor's returns
    assert sum(_crop_sizes(by_direction)) < sum(_crop_sizes(top_view))


@pytest.mark.slow  # a georeferenced pair streamed and compared lean (~9 CPU s): make test-slow
def test_a_georeferenced_pair_with_non_finite_rows_streams_like_the_lean_one(tmp_path) -> None:
    """One station, survey-sized coordinates; NaN rows in the reference keep their place and
    come out unobserved, everything else as the lean comparison has it."""
    paths = _write_pair(tmp_path, 1, 5, shift=452_000.0)
    reference = read_point_cloud(paths[0]).points.copy()
    holes = np.arange(5, len(reference), 997)
    reference[holes] = np.nan
    paths[0].write_bytes(ply_bytes(reference))
    n_points = len(reference) - len(holes) + len(read_point_cloud(paths[1]))
    tiled = _lean_tiled(paths, int(0.6 * n_points))
    streamed = _assert_streamed_equals_lean(paths, tmp_path, n_points, tiled)
    assert len(streamed.reference_label) == len(reference)
    assert np.all(np.asarray(streamed.reference_label)[holes] == -1)


def test_a_streamed_comparison_on_subsamples_finds_the_same_changes(
    tmp_path, three_station_pair, monkeypatch
) -> None:
    """Clouds larger than the subsample: the stages see a sixth of the pair, the tiles all of
    it, and the changes found are the lean comparison's."""
    from app.core.tiling import streamed as module

    paths, n_points, tiled = three_station_pair
    seen: list[int] = []
    original = module.load_pair

    def spy(reference: PointCloud, scan: PointCloud, **options):
        seen.extend([len(reference), len(scan)])
        return original(reference, scan, **options)

    monkeypatch.setattr(module, "load_pair", spy)
    streamed = compare_streamed(
        *paths,
        work_dir=tmp_path / "work",
        max_crop_points=int(0.6 * n_points),
        subsample_points=n_points // 6,
        progress=lambda stage, fraction: None,
        **OPTIONS,
    )
    # about one point in six, drawn by a hash (not every sixth: subsample_offsets)
    assert seen and seen[0] <= 1.01 * n_points / 6, "the stages saw more than the subsample"
    assert len(streamed.reference_label) == len(read_point_cloud(paths[0]))
    for side in ("reference", "scan"):
        ours = np.asarray(getattr(streamed, f"{side}_label")) == LABEL_CHANGED
        theirs = getattr(tiled, f"{side}_label") == LABEL_CHANGED
        union = np.count_nonzero(ours | theirs)
        assert union == 0 or np.count_nonzero(ours & theirs) / union >= 0.95, side
    assert [region.kind for region in streamed.regions] == [region.kind for region in tiled.regions]
    assert streamed.changed == tiled.changed


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


def _ring_ordered_survey(tmp_path: Path, random_state: int):
    """A 200k-point three-station room survey written station by station, ring by ring."""
    return write_lidar_pair(
        tmp_path,
        layout="room",
        change="none",
        n_stations=3,
        angular_step_deg=steps_for_points(200_000, 3),
        random_state=random_state,
    )


@pytest.mark.parametrize("random_state", [5, 6])
def test_a_file_in_scan_order_keeps_its_stations_in_the_subsample(tmp_path, random_state) -> None:
    # a survey written station by station, ring by ring (as scanners write them): every 20th
    # point of such a file keeps no two points of one column, and no station was recovered
    # from it (the 100M pair, issue 30); the hashed subsample keeps them all
    written = _ring_ordered_survey(tmp_path, random_state)
    cloud, subsample, _ = survey(written.reference_path, None, 10_000)
    assert cloud.step == 20
    whole = np.concatenate([points for _, points in cloud.chunks()])
    assert recover_stations(whole[:: cloud.step], random_state=0).origins.shape[0] == 0
    found = recover_stations(subsample, random_state=0).origins
    true = np.load(written.truth_path)["reference_origins"]
    assert found.shape[0] == 3
    nearest = np.linalg.norm(found[:, None, :2] - true[None, :, :2], axis=2).min(axis=1)
    assert np.all(nearest < 0.05)


@pytest.mark.parametrize("random_state", [5, 6])
def test_a_sparse_subsample_searches_its_stations_on_whole_voxels(tmp_path, random_state) -> None:
    # one point in 50 (as at 100M points a file) keeps too few pairs of one column: the
    # stations are searched on the survey's whole voxels at full density, in the subsample's
    # frame, also when the cloud is moved (the scan's aligned frame)
    written = _ring_ordered_survey(tmp_path, random_state)
    _, subsample, voxels = survey(written.reference_path, None, 4_000)
    true = np.load(written.truth_path)["reference_origins"]
    options = {"given": None, "from_file": None, "estimate": True, "recover": "auto"}
    alone = PointCloud(subsample, None, len(subsample))  # type: ignore[arg-type]
    assert resolve_stations("scan", subsample, station_of=alone, **options).source != "recovered"
    whole = PointCloud(subsample, None, len(subsample), sampling_points=voxels)  # type: ignore[arg-type]
    found = resolve_stations("scan", subsample, station_of=whole, **options)
    assert found.source == "recovered"
    turn = np.radians(30.0)
    transform = np.eye(4)
    transform[:2, :2] = [[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]]
    transform[:3, 3] = [2.0, -1.0, 0.0]
    moved = resolve_moved_cloud("scan", subsample, transform, station_of=whole, **options)
    expected_moved = apply_transform(true, transform)
    for origins, expected in ((found.origin, true), (moved.origin, expected_moved)):
        origins = np.asarray(origins).reshape(-1, 3)
        assert origins.shape[0] == 3
        offsets = origins[:, None, :2] - expected[None, :, :2]
        assert np.all(np.linalg.norm(offsets, axis=2).min(axis=1) < 0.05)
