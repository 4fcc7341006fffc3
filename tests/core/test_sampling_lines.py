"""Surfaces a ring lidar samples in lines: a floor or a box top seen as strips far apart.

A spinning lidar on a robot samples a floor (or a box's top, seen from a little above) in ring
lines tens of centimetres apart, each dense along itself.  Rules checked:

* :func:`~app.core.localise.gaps.between_samples`: a place on the plane between two strips of
  samples lies on that surface; a place past the last strip, or off the plane, does not;
* the ray test with a ``gap_radius`` (the trajectory test's): a ray crossing a removed box's
  top between the own cloud's strips crosses its surface, so the top is seen through; without
  it (the ray met the plane where no own sample lies near) the top is only seen edge-on;
* :func:`~app.core.localise.gaps.on_sampled_planes`: a removed box's foot, a few centimetres
  over a floor the other epoch saw in lines 0.3 m apart, lies on that floor (its distance is
  its height over the floor's plane, not the 13 cm to the nearest line).
"""

from __future__ import annotations

import numpy as np
import pytest
from pykdtree.kdtree import KDTree

from app.core.datasets.lidar import LidarWorld, lidar_directions
from app.core.labels import LABEL_CHANGED, LABEL_UNCHANGED
from app.core.localise.changes import localise_changes
from app.core.localise.epoch import EpochCloud
from app.core.localise.gaps import between_samples, on_sampled_planes
from app.core.localise.rays import STATUS_EDGE_ON, STATUS_SEEN_THROUGH
from app.core.localise.surface import local_geometry
from tests.helpers.ray_cases import face_candidates, ray_test, status_seen_by


def strips(
    centres: list[float], *, height: float, length: float = 1.0, across_x: bool = False
) -> np.ndarray:
    """Strips of 3 rows 2 cm apart along x (samples every 2 cm) at the given y centres (along y
    at the given x centres with ``across_x``), at ``height``, shape (n, 3)."""
    along = np.arange(-0.5 * length, 0.5 * length + 1e-9, 0.02)
    rows = []
    for centre in centres:
        for row in (-0.02, 0.0, 0.02):
            rows.append(np.column_stack([along, np.full(along.size, centre + row)]))
    flat = np.vstack(rows)
    if across_x:
        flat = flat[:, ::-1]
    return np.column_stack([flat, np.full(flat.shape[0], height)])


def test_a_place_between_two_strips_of_a_plane_lies_on_it() -> None:
    cloud = local_geometry(strips([-0.12, 0.13], height=0.0), 10)
    places = np.array(
        [
            [0.0, 0.0, 0.0],  # between the strips
            [0.2, 0.01, 0.005],  # between them, within the tolerance of the plane
            [0.0, 0.32, 0.0],  # 17 cm past the last strip
            [0.0, 0.0, 0.08],  # above the plane
        ]
    )
    normal = np.tile([0.0, 0.0, 1.0], (len(places), 1))

    surrounded = between_samples(places, normal, cloud, radius=0.2, tolerance=0.03)

    np.testing.assert_array_equal(surrounded, [True, True, False, False])


def test_samples_farther_than_the_radius_do_not_surround() -> None:
    cloud = local_geometry(strips([-0.3, 0.3], height=0.0), 10)

    surrounded = between_samples(
        np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), cloud, radius=0.2, tolerance=0.03
    )

    assert not surrounded.any()


BOX_TOP = 0.5
SENSOR = np.array([-2.5, 0.0, 1.2])
"""Sees the box's top (x -0.3..0.3, y -0.35..0.35) at 70-80 degrees incidence."""


def top_status(gap_radius: float) -> np.ndarray:
    """Ray status of a removed box's top (its two inner strips: the outer ones are its
    edges), its own cloud strips 20 cm apart across the sensor's view, seen by a lidar whose
    world no longer holds the box."""
    own_points = strips([-0.3, -0.1, 0.1, 0.3], height=BOX_TOP, length=0.7, across_x=True)
    own = local_geometry(own_points, 10)
    chosen = np.flatnonzero((np.abs(own_points[:, 1]) <= 0.2) & (np.abs(own_points[:, 0]) <= 0.15))
    directions = lidar_directions(1.0, 0.25)
    world = LidarWorld(
        shell_low=np.array([-10.0, -10.0, 0.0]),
        shell_high=np.array([10.0, 10.0, 4.0]),
        box_low=np.empty((0, 3)),
        box_high=np.empty((0, 3)),
    )
    distance, _ = world.cast(SENSOR, directions)
    other_points = SENSOR + distance[:, None] * directions
    surface_distance, _ = KDTree(other_points).query(own_points[chosen], k=1)
    candidates = face_candidates(own_points, own, chosen, (0.0, 0.0, 1.0), surface_distance)
    test = ray_test(0.03, gap_radius=gap_radius)
    status = status_seen_by(candidates, own, other_points, SENSOR, test)
    return status


def test_a_removed_box_top_sampled_in_strips_is_seen_through_between_them() -> None:
    status = top_status(gap_radius=0.2)

    assert (status == STATUS_SEEN_THROUGH).all(), np.unique(status, return_counts=True)


def test_without_a_gap_radius_rays_between_the_strips_are_no_evidence() -> None:
    status = top_status(gap_radius=0.0)

    assert (status == STATUS_EDGE_ON).all(), np.unique(status, return_counts=True)


def grid(x: tuple[float, float], y: tuple[float, float], z: tuple[float, float], step: float):
    """Points every ``step`` metres on the axis-aligned rectangle spanned by the ranges (one of
    them a single value), shape (n, 3)."""
    axes = [np.arange(low, high + 1e-9, step) if high > low else [low] for low, high in (x, y, z)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


BOX_HALF, BOX_HEIGHT = 0.15, 0.5


def box_over_lines(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(reference, scan): a dense floor and a box standing on it, 0.3 m square; the scan lost
    the box and saw the floor in strips 0.3 m apart, the box's faces midway between them."""
    rng = np.random.default_rng(seed)
    floor = grid((-1.5, 1.5), (-1.5, 1.5), (0.0, 0.0), 0.03)
    floor = floor[(np.abs(floor[:, :2]) > BOX_HALF).any(axis=1)]
    sides = [
        grid((low, high), (-BOX_HALF, BOX_HALF), (0.01, BOX_HEIGHT), 0.03)
        for low, high in ((-BOX_HALF, -BOX_HALF), (BOX_HALF, BOX_HALF))
    ] + [
        grid((-BOX_HALF, BOX_HALF), (low, high), (0.01, BOX_HEIGHT), 0.03)
        for low, high in ((-BOX_HALF, -BOX_HALF), (BOX_HALF, BOX_HALF))
    ]
    top = grid((-BOX_HALF, BOX_HALF), (-BOX_HALF, BOX_HALF), (BOX_HEIGHT, BOX_HEIGHT), 0.03)
    reference = np.vstack([floor, *sides, top])
    scan = strips([-1.2, -0.9, -0.6, -0.3, 0.0, 0.3, 0.6, 0.9, 1.2], height=0.0, length=3.0)
    noise = 0.003
    return (
        reference + rng.normal(0.0, noise, reference.shape),
        scan + rng.normal(0.0, noise, scan.shape),
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_removed_box_foot_over_a_floor_seen_in_lines_is_on_the_floor(seed: int) -> None:
    """The box's foot (under 6 cm up) lies within the change threshold of the floor, though its
    nearest floor sample is 13 cm away across the gap between two lines: unchanged; the box
    above 20 cm stays removed."""
    reference, scan = box_over_lines(seed)
    on_box = (np.abs(reference[:, :2]) <= BOX_HALF + 0.01).all(axis=1) & (reference[:, 2] > 0.005)
    foot = on_box & (reference[:, 2] < 0.06) & (np.abs(reference[:, :2]) > 0.1).any(axis=1)
    nearest, _ = KDTree(scan).query(reference[foot], k=1)
    assert np.median(nearest) > 0.11  # the floor's samples are far: only its plane is near

    found = localise_changes(reference, scan)

    foot_label = found.reference_label[foot]
    assert (foot_label == LABEL_UNCHANGED).all(), np.unique(foot_label, return_counts=True)
    assert (found.reference_distance[foot] <= 0.1).all()  # within the change threshold
    upper = on_box & (reference[:, 2] > 0.2)
    assert np.mean(found.reference_label[upper] == LABEL_CHANGED) > 0.9


def test_a_station_clouds_candidates_keep_their_measured_distance() -> None:
    """The rule is for maps from a moving sensor: against a scan from one known station (its
    rays model the sensor), the foot keeps the distance to its nearest floor line: a
    candidate for the ray test, not unchanged surface."""
    reference, scan = box_over_lines(0)
    on_box = (np.abs(reference[:, :2]) <= BOX_HALF + 0.01).all(axis=1) & (reference[:, 2] > 0.005)
    foot = on_box & (reference[:, 2] < 0.06) & (np.abs(reference[:, :2]) > 0.1).any(axis=1)

    found = localise_changes(reference, EpochCloud(scan, origin=np.array([0.0, -2.5, 1.0])))

    assert np.mean(found.reference_label[foot] == LABEL_UNCHANGED) < 0.5


def test_skipping_candidates_with_no_sample_within_reach_gives_the_same_planes() -> None:
    reference, scan = box_over_lines(1)
    other = local_geometry(scan, 10)
    nearest, _ = KDTree(scan).query(reference, k=1)
    candidate = nearest > 0.1
    settings = {"radius": 0.2, "tolerance": 0.03, "change_threshold": 0.1}
    distance_all, distance_near = nearest.copy(), nearest.copy()

    kept_all = on_sampled_planes(reference, distance_all, candidate, other, **settings)
    kept_near = on_sampled_planes(
        reference, distance_near, candidate, other, nearest_distance=nearest, **settings
    )

    assert 0 < np.count_nonzero(candidate & ~kept_all) < np.count_nonzero(candidate)
    assert (nearest[candidate] > 0.2).any()  # some candidates are skipped
    np.testing.assert_array_equal(kept_near, kept_all)
    np.testing.assert_array_equal(distance_near, distance_all)
