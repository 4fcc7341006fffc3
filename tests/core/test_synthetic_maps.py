"""Synthetic moving-sensor maps (issue 29's test classes): determinism, truth, thinning, times."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from app.core.datasets.map_world import SensorModel, cast_rays, far_from_surfaces, voxel_thin
from app.core.datasets.maps import MAP_CLASSES, map_pair

SMALL = {"rgbd": 0.03, "robot": 0.03, "tls": 0.12}
"""``size`` of the test pairs: a few thousand points an epoch (terrestrial: 15-20 thousand, so
that its coarse dome grid still puts a few dozen points on a removed box)."""
LAYOUT = {"rgbd": "room", "robot": "office", "tls": "office"}


def build_pair(map_class: str, change: str, seed: int, misaligned: bool, layout: str | None):
    """A fresh small pair."""
    return map_pair(
        map_class,
        layout=layout or LAYOUT[map_class],
        change=change,
        misaligned=misaligned,
        size=SMALL[map_class],
        random_state=seed,
    )


@cache
def small_pair(
    map_class: str, change: str, seed: int = 0, misaligned: bool = False, layout: str | None = None
):
    """A small pair, built once per test session (tests only read it)."""
    return build_pair(map_class, change, seed, misaligned, layout)


@pytest.mark.parametrize("map_class", MAP_CLASSES)
def test_same_seed_same_pair(map_class: str) -> None:
    first = small_pair(map_class, "moved", seed=3)
    again = build_pair(map_class, "moved", 3, False, None)
    np.testing.assert_array_equal(first.reference.points, again.reference.points)
    np.testing.assert_array_equal(first.scan.points, again.scan.points)
    np.testing.assert_array_equal(first.scan_changed, again.scan_changed)
    np.testing.assert_array_equal(first.reference_scored, again.reference_scored)
    np.testing.assert_array_equal(first.scan.attributes["time"], again.scan.attributes["time"])
    assert [change.name for change in first.changes] == [change.name for change in again.changes]


@pytest.mark.parametrize("map_class", MAP_CLASSES)
def test_unchanged_pair_has_no_changed_point(map_class: str) -> None:
    pair = small_pair(map_class, "none", seed=1, misaligned=True)
    assert pair.changes == []
    assert not pair.reference_changed.any()
    assert not pair.scan_changed.any()
    assert pair.reference_scored.mean() > 0.5  # the other path saw most of the place


@pytest.mark.parametrize("map_class", MAP_CLASSES)
def test_removed_object_is_changed_and_scored_where_the_scan_saw_its_place(
    map_class: str,
) -> None:
    pair = small_pair(map_class, "removed", seed=2)
    (removed,) = pair.changes
    assert removed.kind == "removed" and removed.scan_box is None
    on_object = pair.reference_change == 0
    assert on_object.any()
    # only the removed object's points can be changed, and most of them are
    assert not (pair.reference_changed & ~on_object).any()
    assert not pair.scan_changed.any()
    assert pair.reference_changed[on_object].mean() > 0.5
    # an exact point of the removed object is more than 10 cm from every surface of the scan
    distance = pair.scan_world.surface_distance(pair.reference_exact[pair.reference_changed])
    assert (distance > 0.1).all()
    assert (pair.reference_changed & pair.reference_scored).sum() >= 10


def test_scored_matches_ray_casting_from_every_station() -> None:
    """Terrestrial stations are dome lidars: ``scored`` is what LidarWorld.visible_from says."""
    pair = small_pair("tls", "removed", seed=2)
    stations = pair.scan.trajectory.positions
    observed = np.zeros(len(pair.reference_exact), dtype=bool)
    for station in stations:
        observed |= pair.scan_world.visible_from(station, pair.reference_exact)
    assert pair.visibility_stride == 1
    assert np.mean(observed != pair.reference_scored) < 0.002
    assert 0.3 < pair.reference_scored.mean() <= 1.0


def test_voxel_thinning_keeps_one_point_per_voxel() -> None:
    rng = np.random.default_rng(0)
    points = rng.uniform(0.0, 0.5, (20_000, 3))
    centroids, kept = voxel_thin(points, 0.05)
    cells = np.floor(centroids / 0.05).astype(np.int64)
    assert len(np.unique(cells, axis=0)) == len(centroids) == 1000
    np.testing.assert_array_equal(np.floor(points[kept] / 0.05).astype(np.int64), cells)


@pytest.mark.parametrize("map_class", MAP_CLASSES)
def test_thinned_map_density_is_bounded(map_class: str) -> None:
    pair = small_pair(map_class, "moved", seed=3)
    voxel = pair.metadata["voxel"]
    # any cube of the voxel's size meets at most 8 cells of the thinning grid, one point each
    points = pair.reference.points
    _, counts = np.unique(np.floor(points / voxel).astype(np.int64), axis=0, return_counts=True)
    assert counts.max() <= 8


@pytest.mark.parametrize("map_class", MAP_CLASSES)
def test_times_lie_on_the_trajectory_and_its_pose_sees_the_point(map_class: str) -> None:
    pair = small_pair(map_class, "moved", seed=3)
    cloud = pair.reference
    trajectory = cloud.trajectory
    times = cloud.attributes["time"]
    assert times.dtype == np.float64
    assert times.min() >= trajectory.times[0] and times.max() <= trajectory.times[-1]
    pose = np.searchsorted(trajectory.times, times)
    np.testing.assert_array_equal(trajectory.times[pose], times)  # a frame's or sweep's time
    assert len(np.unique(pose)) > 1
    rotations = Rotation.from_quat(trajectory.orientations).as_matrix()
    if map_class == "rgbd":
        sensor = SensorModel("frustum", (0.29, 5.01), 30.5, (-23.0, 23.0))
    elif map_class == "robot":
        low, high = (-15.0, 15.0) if pair.metadata["rings"] == 16 else (-25.0, 15.0)
        sensor = SensorModel("lidar", (0.45, 60.5), 180.0, (low - 0.5, high + 0.5))
    else:
        sensor = SensorModel("lidar", (0.25, 120.5), 180.0, (-45.5, 60.5))
    exact = pair.reference_exact
    in_view = np.zeros(len(exact), dtype=bool)
    for number in np.unique(pose):
        rows = np.flatnonzero(pose == number)
        in_view[rows] = sensor.in_view(trajectory.positions[number], rotations[number], exact[rows])
    assert in_view.all()
    origins = trajectory.positions[pose]
    offset = exact - origins
    distance = np.linalg.norm(offset, axis=1)
    first, _ = cast_rays(pair.reference_world, origins, offset / distance[:, None])
    assert (first >= distance - 0.05).mean() > 0.999  # nothing before the point (pose errors)


def test_files_without_trajectory_carry_no_times() -> None:
    pair = small_pair("robot", "none", seed=1, misaligned=True)
    reference, scan = pair.clouds()
    assert reference.trajectory is None and scan.trajectory is None
    assert "time" not in reference.attributes and "time" not in scan.attributes
    np.testing.assert_array_equal(reference.points, pair.reference.points)
    with_times = pair.clouds(with_trajectory=True)
    assert with_times[1].trajectory is not None and "time" in with_times[1].attributes


@pytest.mark.parametrize("map_class", MAP_CLASSES)
def test_misalignment_is_applied_as_stated(map_class: str) -> None:
    aligned = small_pair(map_class, "removed", seed=2)
    np.testing.assert_allclose(aligned.true_transform, np.eye(4), atol=1e-12)
    pair = small_pair(map_class, "none", seed=1, misaligned=True)
    transform = pair.true_transform
    angle = np.degrees(Rotation.from_matrix(transform[:3, :3]).magnitude())
    assert angle == pytest.approx(0.3, abs=1e-6)
    # the scan file is off by centimetres; put back, it lies on the truth's surfaces
    put_back = pair.scan.points @ transform[:3, :3].T + transform[:3, 3]
    before = np.median(np.linalg.norm(pair.scan.points - pair.scan_exact, axis=1))
    after = np.median(np.linalg.norm(put_back - pair.scan_exact, axis=1))
    assert before > 0.015
    assert after < 0.012
    centre = pair.scan_exact.mean(axis=0)
    shift = np.linalg.norm(centre @ transform[:3, :3].T + transform[:3, 3] - centre)
    assert 0.005 < shift < 0.06


def test_moved_and_rotated_objects() -> None:
    moved = small_pair("rgbd", "moved", seed=3).changes[0]
    assert moved.kind == "moved"
    centres = [(low + high) / 2.0 for low, high in (moved.reference_box, moved.scan_box)]
    assert np.linalg.norm(centres[0][:2] - centres[1][:2]) >= 0.5
    turned = small_pair("robot", "rotated", seed=10).changes[0]
    assert turned.kind == "rotated"
    reference_size = turned.reference_box[1] - turned.reference_box[0]
    scan_size = turned.scan_box[1] - turned.scan_box[0]
    np.testing.assert_allclose(reference_size[[1, 0, 2]], scan_size, atol=1e-9)


def test_paths_of_the_two_epochs_differ() -> None:
    pair = small_pair("robot", "none", seed=11, layout="corridor")
    reference = pair.reference.trajectory.positions
    scan = pair.scan.trajectory.positions
    assert len(reference) > 3 and len(scan) > 3
    start_gap = np.linalg.norm(reference[0] - scan[0])
    assert start_gap > 1.0 or len(reference) != len(scan)


def test_bad_arguments_say_what_to_fix() -> None:
    with pytest.raises(ValueError, match="map_class"):
        map_pair("sonar")
    with pytest.raises(ValueError, match="layout"):
        map_pair("rgbd", layout="warehouse")
    with pytest.raises(ValueError, match="change"):
        map_pair("robot", change="exploded", size=SMALL["robot"])


def test_casting_with_object_bounds_gives_the_same_hits() -> None:
    pair = small_pair("rgbd", "moved", seed=3)
    world = pair.reference_world
    rng = np.random.default_rng(1)
    origin = (world.shell_low + world.shell_high) / 2.0
    origin[2] = world.shell_low[2] + 1.7
    directions = rng.normal(size=(3000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    expected_distance, expected_box = world.cast(origin, directions)
    origins = np.broadcast_to(origin, directions.shape)
    owner = np.repeat(np.arange(len(world.box_low)), 1)
    for groups in (None, owner // 3):
        distance, box = cast_rays(world, origins, directions, groups)
        np.testing.assert_allclose(distance, expected_distance, rtol=1e-12)
        np.testing.assert_array_equal(box, expected_box)
    assert (expected_box >= 0).any()


def test_far_from_surfaces_is_the_surface_distance_test() -> None:
    pair = small_pair("rgbd", "moved", seed=3)
    world = pair.scan_world
    rng = np.random.default_rng(2)
    points = rng.uniform(world.shell_low, world.shell_high, (20_000, 3))
    points = np.vstack([points, pair.reference_exact])
    np.testing.assert_array_equal(
        far_from_surfaces(world, points, 0.1), world.surface_distance(points) > 0.1
    )
