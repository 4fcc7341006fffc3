"""The synthetic scenes: shapes, ground truth and the exactness of the ray casting."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.datasets.scenes import (
    CORRIDOR_BOX_DEPTH,
    LIDAR_ELEVATION_DEG,
    ROOM_MAX,
    ROOM_MIN,
    STATIC_BOXES,
    SyntheticPair,
    paper_corridor,
    raycast_scene,
    raycast_scene_objects,
)

SCENE_POINTS = 20_000


def assert_pair_shapes(pair: SyntheticPair) -> None:
    n, m = len(pair.reference), len(pair.scan)
    assert pair.reference.shape == (n, 3) and pair.reference.dtype == np.float64
    assert pair.scan.shape == (m, 3) and pair.scan.dtype == np.float64
    for mask, size in (
        (pair.reference_changed, n),
        (pair.reference_observed, n),
        (pair.scan_changed, m),
        (pair.scan_observed, m),
    ):
        assert mask.shape == (size,) and mask.dtype == np.bool_
    assert pair.reference_origin.shape == (3,) and pair.scan_origin.shape == (3,)
    assert pair.true_transform.shape == (4, 4)
    rotation = pair.true_transform[:3, :3]
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(pair.true_transform[3], [0, 0, 0, 1])


def rotation_angle_deg(rotation: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(rotation) - 1) / 2, -1, 1))))


# --- paper corridor ----------------------------------------------------------------------------


def test_corridor_without_change_is_two_noisy_copies_of_the_same_points():
    pair = paper_corridor(n_points=300, noise_variance=1e-4, random_state=0)
    assert_pair_shapes(pair)
    assert len(pair.reference) == len(pair.scan) == 300
    assert not pair.reference_changed.any() and not pair.scan_changed.any()
    assert pair.reference_observed.all() and pair.scan_observed.all()
    np.testing.assert_array_equal(pair.true_transform, np.eye(4))
    np.testing.assert_array_equal(pair.reference_origin, [0.0, 0.0, 1.0])
    difference = pair.scan - pair.reference  # noise of both clouds: variance 2e-4 per axis
    assert difference.var() == pytest.approx(2e-4, rel=0.2)


def test_corridor_noise_free_points_lie_on_the_walls_and_ceiling():
    pair = paper_corridor(n_points=301, noise_variance=0.0, random_state=1)
    points = pair.reference
    on_wall = np.isclose(np.abs(points[:, 0]), 1.0)
    on_ceiling = np.isclose(points[:, 2], 2.0)
    assert (on_wall | on_ceiling).all()
    assert np.isclose(points[:, 0], -1.0).sum() == 101  # the remainder point goes to a wall
    assert (np.abs(points[:, 1]) <= 2.0).all() and (points[:, 2] >= 0).all()


@pytest.mark.parametrize("change_fraction", [0.03, 0.1, 0.33])
def test_corridor_box_moves_a_square_patch_of_one_wall_into_the_corridor(change_fraction):
    pair = paper_corridor(
        n_points=300, noise_variance=0.0, change_fraction=change_fraction, random_state=2
    )
    changed = pair.scan_changed
    assert changed.sum() == round(change_fraction * 300)
    np.testing.assert_array_equal(pair.reference_changed, changed)
    # the moved points were on the wall x = -1 and now form the box front at x = -0.5
    np.testing.assert_allclose(pair.reference[changed, 0], -1.0)
    np.testing.assert_allclose(pair.scan[changed, 0], -1.0 + CORRIDOR_BOX_DEPTH)
    np.testing.assert_allclose(pair.scan[changed, 1:], pair.reference[changed, 1:])
    np.testing.assert_array_equal(pair.scan[~changed], pair.reference[~changed])
    # a square patch around the wall's centre: no unmoved wall point is nearer (Chebyshev)
    chebyshev = np.maximum(np.abs(pair.reference[:, 1]), np.abs(pair.reference[:, 2] - 1.0))
    left_wall = np.isclose(pair.reference[:, 0], -1.0)
    assert chebyshev[changed].max() <= chebyshev[left_wall & ~changed].min()


def test_corridor_rejects_a_box_larger_than_its_wall():
    with pytest.raises(ValueError, match="change_fraction"):
        paper_corridor(change_fraction=0.4)
    with pytest.raises(ValueError, match="n_points"):
        paper_corridor(n_points=5)


def test_corridor_is_reproducible():
    first = paper_corridor(change_fraction=0.1, random_state=7)
    second = paper_corridor(change_fraction=0.1, random_state=7)
    np.testing.assert_array_equal(first.reference, second.reference)
    np.testing.assert_array_equal(first.scan, second.scan)


# --- ray-cast scene ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def noise_free_mixed() -> SyntheticPair:
    return raycast_scene(
        n_points=SCENE_POINTS, change="mixed", range_noise=0.0, sensor_shift=1.0, random_state=4
    )


def distance_to_scene_surfaces(points: np.ndarray, boxes) -> np.ndarray:
    """Distance of each point to the nearest room wall/floor/ceiling or box face."""
    shell = np.minimum(np.abs(points - ROOM_MIN), np.abs(points - ROOM_MAX)).min(axis=1)
    best = shell
    for box in boxes:
        low, high = np.asarray(box.low), np.asarray(box.high)
        inside_span = (points >= low - 1e-9) & (points <= high + 1e-9)
        for axis in range(3):
            others = [a for a in range(3) if a != axis]
            on_face_span = inside_span[:, others].all(axis=1)
            face_gap = np.minimum(
                np.abs(points[:, axis] - low[axis]), np.abs(points[:, axis] - high[axis])
            )
            best = np.where(on_face_span, np.minimum(best, face_gap), best)
    return best


def test_raycast_shapes_and_exact_surfaces(noise_free_mixed):
    pair = noise_free_mixed
    assert_pair_shapes(pair)
    assert len(pair.reference) == len(pair.scan) == SCENE_POINTS
    reference_only, scan_only = raycast_scene_objects("mixed")
    reference_world = [*STATIC_BOXES, *reference_only]
    scan_world = [*STATIC_BOXES, *scan_only]
    assert distance_to_scene_surfaces(pair.reference, reference_world).max() < 1e-9
    assert distance_to_scene_surfaces(pair.aligned_scan(), scan_world).max() < 1e-9


def test_raycast_lidar_pattern_density_falls_with_range(noise_free_mixed):
    pair = noise_free_mixed
    offset = pair.reference - pair.reference_origin
    distance = np.linalg.norm(offset, axis=1)
    elevation = np.degrees(np.arcsin(offset[:, 2] / distance))
    low, high = LIDAR_ELEVATION_DEG
    assert elevation.min() >= low - 1.0 and elevation.max() <= high + 1.0
    # equal angular sampling: points per metre of range fall off with range
    near = ((distance > 2) & (distance < 3)).sum()
    far = ((distance > 6) & (distance < 7)).sum()
    assert near > far


def test_raycast_ground_truth_of_each_change_kind():
    sizes = {}
    for change in ("none", "box", "removed", "moved"):
        pair = raycast_scene(n_points=SCENE_POINTS, change=change, random_state=5)
        sizes[change] = (int(pair.reference_changed.sum()), int(pair.scan_changed.sum()))
        reference_only, scan_only = raycast_scene_objects(change)
        for boxes, points, changed in (
            (reference_only, pair.reference, pair.reference_changed),
            (scan_only, pair.aligned_scan(), pair.scan_changed),
        ):
            if not boxes:
                assert not changed.any()
                continue
            # changed points are exactly the points on the changing objects (noise 1 cm)
            inside = np.zeros(len(points), dtype=bool)
            for box in boxes:
                inside |= np.all(
                    (points > np.asarray(box.low) - 0.05) & (points < np.asarray(box.high) + 0.05),
                    axis=1,
                )
            assert changed.sum() > 200
            assert inside[changed].all()
    assert sizes["box"][0] == 0 and sizes["removed"][1] == 0
    assert min(sizes["moved"]) > 200


def test_raycast_observed_masks_follow_the_other_world():
    added = raycast_scene(n_points=SCENE_POINTS, change="box", sensor_shift=0.5, random_state=6)
    box = raycast_scene_objects("box")[1][0]
    low, high = np.asarray(box.low), np.asarray(box.high)
    # reference floor points under the new box: the scan's rays hit the box first
    under = np.all((added.reference[:, :2] > low[:2]) & (added.reference[:, :2] < high[:2]), 1)
    under &= added.reference[:, 2] < 0.05
    assert under.sum() > 10
    assert not added.reference_observed[under].any()
    # the added box itself is visible from the reference sensor: its points are observed
    assert added.scan_observed[added.scan_changed].mean() > 0.9

    removed = raycast_scene(
        n_points=SCENE_POINTS, change="removed", sensor_shift=0.5, random_state=6
    )
    # the scan sensor sees through where the removed box stood: its points are observed
    assert removed.reference_observed[removed.reference_changed].mean() > 0.7


def test_raycast_sensor_at_the_same_place_sees_every_reference_point():
    pair = raycast_scene(n_points=SCENE_POINTS, change="none", sensor_shift=0.0, random_state=8)
    assert pair.reference_observed.mean() > 0.999
    assert pair.scan_observed.mean() > 0.999


def test_raycast_pose_error_and_true_transform():
    translation, rotation = 0.03, 0.4
    pair = raycast_scene(
        n_points=5000,
        change="none",
        sensor_shift=1.0,
        pose_error=(translation, rotation),
        random_state=9,
    )
    transform = pair.true_transform
    assert rotation_angle_deg(transform[:3, :3]) == pytest.approx(rotation, abs=1e-9)
    # the error rotates about the scan sensor, so the sensor moves by the translation only
    aligned_origin = pair.aligned_scan_origin()
    assert np.linalg.norm(pair.scan_origin - aligned_origin) == pytest.approx(translation)
    assert np.linalg.norm(aligned_origin - pair.reference_origin) == pytest.approx(1.0)
    assert aligned_origin[2] == pytest.approx(pair.reference_origin[2])
    # the scan is expressed in its own frame: not aligned until transformed
    assert np.abs(pair.scan - pair.aligned_scan()).max() > 0.02


def test_raycast_is_reproducible_and_validates():
    first = raycast_scene(n_points=2000, change="moved", random_state=3)
    second = raycast_scene(n_points=2000, change="moved", random_state=3)
    np.testing.assert_array_equal(first.scan, second.scan)
    np.testing.assert_array_equal(first.reference_observed, second.reference_observed)
    with pytest.raises(ValueError, match="change"):
        raycast_scene(n_points=2000, change="teleported")
    with pytest.raises(ValueError, match="sensor_shift"):
        raycast_scene(n_points=2000, sensor_shift=20.0)


@pytest.mark.slow
def test_raycast_200k_full_size_scene():
    """Full size; its generation time is a benchmark figure (bench/scenes.py), not a test."""
    pair = raycast_scene(n_points=200_000, change="mixed", pose_error=(0.03, 0.4), random_state=1)
    assert len(pair.reference) == len(pair.scan) == 200_000
    assert pair.reference_changed.any() and pair.scan_changed.any()
    assert not pair.reference_observed.all()  # furniture occludes part of the room
