"""The issue-15 scene generator: shapes, determinism, the lidar's regular grid and the truth."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.datasets.lidar import (
    CHANGE_DISTANCE,
    ELEVATION_RANGE_DEG,
    LAYOUTS,
    SENSOR_HEIGHT_RANGE,
    lidar_directions,
    lidar_pair,
    steps_for_points,
)

STEP = 1.5  # coarse grid: fast tests


def _angles(points: np.ndarray, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    offset = points - origin
    elevation = np.rad2deg(np.arctan2(offset[:, 2], np.hypot(offset[:, 0], offset[:, 1])))
    azimuth = np.rad2deg(np.arctan2(offset[:, 1], offset[:, 0]))
    return elevation, azimuth


def _grid_residual(angles: np.ndarray, step: float) -> np.ndarray:
    phase = angles / step
    return np.abs(phase - np.round(phase)) * step


@pytest.mark.parametrize("layout", LAYOUTS)
def test_shapes_stations_and_file_frame(layout: str) -> None:
    pair = lidar_pair(layout=layout, change="added", angular_step_deg=STEP, random_state=4)
    n, m = len(pair.reference), len(pair.scan)
    assert pair.reference.shape == (n, 3) and pair.scan.shape == (m, 3)
    for mask, size in [
        (pair.reference_changed, n),
        (pair.reference_observed, n),
        (pair.scan_changed, m),
        (pair.scan_observed, m),
    ]:
        assert mask.shape == (size,) and mask.dtype == bool
    assert pair.reference_origins.shape == (1, 3) and pair.scan_origins.shape == (1, 3)
    assert np.all(pair.reference_station == 0)
    # the sensor is away from the file's origin, 0.8-1.5 m above the floor
    assert np.linalg.norm(pair.reference_origin) > 3.0
    floor = np.quantile(pair.reference[:, 2], 0.001)
    height = pair.reference_origin[2] - floor
    assert SENSOR_HEIGHT_RANGE[0] - 0.05 <= height <= SENSOR_HEIGHT_RANGE[1] + 0.05
    shift = np.linalg.norm(pair.scan_origin - pair.reference_origin)
    assert 0.1 - 1e-9 <= shift <= 1.5 + 1e-9


def test_same_seed_same_pair_other_seed_other_pair() -> None:
    first = lidar_pair(layout="room", change="moved", angular_step_deg=STEP, random_state=9)
    again = lidar_pair(layout="room", change="moved", angular_step_deg=STEP, random_state=9)
    other = lidar_pair(layout="room", change="moved", angular_step_deg=STEP, random_state=10)
    np.testing.assert_array_equal(first.reference, again.reference)
    np.testing.assert_array_equal(first.scan_changed, again.scan_changed)
    assert first.reference.shape != other.reference.shape or not np.array_equal(
        first.reference, other.reference
    )


def test_returns_lie_on_a_regular_angular_grid_from_the_true_origin_only() -> None:
    pair = lidar_pair(layout="corridor", change="none", angular_step_deg=(0.8, 0.5), random_state=2)
    elevation, azimuth = _angles(pair.reference, pair.reference_origin)
    assert elevation.min() >= ELEVATION_RANGE_DEG[0] - 1e-6
    assert elevation.max() <= ELEVATION_RANGE_DEG[1] + 1e-6
    assert _grid_residual(elevation - ELEVATION_RANGE_DEG[0], 0.8).max() < 1e-6
    # the columns share one phase: azimuth differences are multiples of the step
    assert _grid_residual(azimuth - azimuth[0], 0.5).max() < 1e-6
    # 5 cm off, the grid smears
    moved = pair.reference_origin + np.array([0.05, 0.0, 0.0])
    elevation, _ = _angles(pair.reference, moved)
    assert np.median(_grid_residual(elevation - ELEVATION_RANGE_DEG[0], 0.8)) > 0.05
    assert lidar_directions(1.0, 1.0).shape == (106 * 360, 3)
    assert abs(steps_for_points(1_000_000) - 0.2) < 0.01


def test_no_change_means_no_changed_point() -> None:
    pair = lidar_pair(layout="warehouse", change="none", angular_step_deg=STEP, random_state=5)
    assert not pair.reference_changed.any() and not pair.scan_changed.any()
    assert pair.reference_observed.mean() > 0.5 and not pair.reference_observed.all()


def test_added_box_changes_only_scan_points_on_one_compact_box() -> None:
    pair = lidar_pair(layout="room", change="added", angular_step_deg=STEP, random_state=6)
    assert not pair.reference_changed.any()
    changed = pair.scan[pair.scan_changed]
    assert len(changed) >= 10
    extent = changed.max(axis=0) - changed.min(axis=0)
    assert np.all(extent <= 1.2 + 0.05)
    # changed points stand off the floor by more than the change distance
    floor = np.quantile(pair.scan[:, 2], 0.001)
    assert changed[:, 2].min() > floor + CHANGE_DISTANCE - 0.05


def test_removed_box_changes_only_reference_points_and_they_are_observed() -> None:
    pair = lidar_pair(layout="room", change="removed", angular_step_deg=STEP, random_state=7)
    assert not pair.scan_changed.any()
    assert np.count_nonzero(pair.reference_changed & pair.reference_observed) >= 10


def test_points_in_the_blind_cone_of_the_other_sensor_are_unobserved() -> None:
    pair = lidar_pair(layout="room", change="none", angular_step_deg=STEP, random_state=8)
    elevation, _ = _angles(pair.reference, pair.scan_origin)
    below = elevation < ELEVATION_RANGE_DEG[0] - 0.5
    assert below.any()
    assert not pair.reference_observed[below].any()


def test_multi_station_epochs_are_shuffled_and_each_station_keeps_its_grid() -> None:
    pair = lidar_pair(
        layout="warehouse", change="added", n_stations=4, angular_step_deg=STEP, random_state=3
    )
    assert pair.reference_origins.shape == (4, 3) and pair.scan_origins.shape == (4, 3)
    assert set(np.unique(pair.reference_station)) == {0, 1, 2, 3}
    assert np.any(np.diff(pair.reference_station) != 0)  # shuffled, not blocks
    assert np.count_nonzero(np.diff(pair.reference_station)) > 100
    for station in range(4):
        mine = pair.reference[pair.reference_station == station]
        elevation, _ = _angles(mine, pair.reference_origins[station])
        assert _grid_residual(elevation - ELEVATION_RANGE_DEG[0], STEP).max() < 1e-6


def test_misalignment_is_small_and_undone_by_the_true_transform() -> None:
    pair = lidar_pair(
        layout="room", change="none", angular_step_deg=STEP, misaligned=True, random_state=11
    )
    rotation = pair.true_transform[:3, :3]
    angle = np.rad2deg(np.arccos(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0)))
    assert 0.3 - 1e-6 <= angle <= 0.4 + 1e-6
    in_world = pair.scan_origin @ rotation.T + pair.true_transform[:3, 3]
    assert 0.1 - 1e-6 <= np.linalg.norm(in_world - pair.reference_origin) <= 1.5 + 1e-6
    assert abs(in_world[2] - pair.reference_origin[2]) < 0.71


def test_bad_arguments_are_refused() -> None:
    with pytest.raises(ValueError, match="layout"):
        lidar_pair(layout="cave")
    with pytest.raises(ValueError, match="change"):
        lidar_pair(change="burnt")
    with pytest.raises(ValueError, match="n_stations"):
        lidar_pair(n_stations=0)
