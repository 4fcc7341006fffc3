"""Opt-in artefacts of real fused RGB-D maps (issue 29): drift, flying pixels, missing patches."""

from __future__ import annotations

import hashlib
from functools import cache

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from app.core.datasets.map_world import CHANGE_DISTANCE, far_from_surfaces
from app.core.datasets.maps import map_pair
from app.core.datasets.rgbd_artefacts import (
    DepthArtefacts,
    drift_errors,
    fly_edge_pixels,
    missing_patches,
)

DEFAULT_PAIR_DIGEST = "d2744584a221f6d0eafb0d752531055f952bf26a79bc345f47f1e83b40fea8bc"
"""SHA-256 of a default small RGB-D pair's points, times and truth, as main drew it before the
artefacts existed (``map_pair("rgbd", change="moved", size=0.03, misaligned=True,
random_state=3)``)."""


@cache
def small_rgbd(realism: str, change: str = "moved", seed: int = 3):
    return map_pair(
        "rgbd", change=change, size=0.03, misaligned=True, realism=realism, random_state=seed
    )


def digest(pair) -> str:
    hashed = hashlib.sha256()
    for array in (
        pair.reference.points,
        pair.scan.points,
        pair.reference.attributes["time"],
        pair.scan_changed,
        pair.reference_scored,
    ):
        hashed.update(np.ascontiguousarray(array).tobytes())
    return hashed.hexdigest()


def test_default_pair_is_unchanged_by_the_option() -> None:
    assert digest(small_rgbd("none")) == DEFAULT_PAIR_DIGEST
    default = map_pair("rgbd", change="moved", size=0.03, misaligned=True, random_state=3)
    assert digest(default) == DEFAULT_PAIR_DIGEST
    assert "drift" not in default.metadata


def test_drift_keeps_the_room_and_change_and_the_world_truth() -> None:
    exact, drifted = small_rgbd("none"), small_rgbd("drift")
    assert drifted.metadata["drift"] == 1.0
    assert [change.name for change in drifted.changes] == [c.name for c in exact.changes]
    np.testing.assert_array_equal(drifted.true_transform, exact.true_transform)
    np.testing.assert_array_equal(drifted.scan_world.box_low, exact.scan_world.box_low)
    # the truth is the world's, from each point's exact surface point
    far = far_from_surfaces(drifted.scan_world, drifted.reference_exact, CHANGE_DISTANCE)
    np.testing.assert_array_equal(drifted.reference_changed, far)
    # the points are not the exact ones: they moved by drift, flying pixels and holes
    same_count = len(drifted.reference.points) == len(exact.reference.points)
    assert not same_count or not np.allclose(drifted.reference.points, exact.reference.points)


def test_drifted_points_stay_near_their_surface_but_some_fly() -> None:
    pair = small_rgbd("drift", change="none", seed=4)
    offset = np.linalg.norm(pair.reference.points - pair.reference_exact, axis=1)
    assert np.median(offset) < 0.01
    # flying pixels: a small share lies well off its surface, in the air
    flying = np.mean(pair.reference_world.surface_distance(pair.reference.points) > 0.1)
    assert 0.0 < flying < 0.03
    assert not pair.reference_changed.any() and not pair.scan_changed.any()


def test_trajectory_is_the_estimated_one() -> None:
    exact, drifted = small_rgbd("none"), small_rgbd("drift")
    true_positions = exact.reference.trajectory.positions
    estimated = drifted.reference.trajectory.positions
    error = np.linalg.norm(estimated - true_positions, axis=1)
    assert error[0] == pytest.approx(0.0, abs=1e-9)
    assert 0.001 < error.max() <= DepthArtefacts().drift_shift[1] + 1e-9


def test_drift_errors_are_smooth_bounded_and_start_at_zero() -> None:
    artefacts = DepthArtefacts()
    rotation, shift = drift_errors(np.random.default_rng(5), 200, artefacts)
    angle = np.degrees(np.linalg.norm(Rotation.from_matrix(rotation).as_rotvec(), axis=1))
    size = np.linalg.norm(shift, axis=1)
    assert size[0] == 0.0 and angle[0] == pytest.approx(0.0, abs=1e-9)
    assert artefacts.drift_shift[0] - 1e-9 <= size.max() <= artefacts.drift_shift[1] + 1e-9
    low, high = artefacts.drift_angle_deg
    assert low - 1e-6 <= angle.max() <= high + 1e-6
    # smooth: one frame's step is a small part of the largest error
    assert np.linalg.norm(np.diff(shift, axis=0), axis=1).max() < 0.2 * size.max()


def test_flying_pixels_lie_between_the_depths_of_an_edge_only() -> None:
    depth = np.full((40, 6, 8), 3.0)
    box = np.full(depth.shape, -1)
    depth[:, :, :4] = 1.0  # a box in front on the left half
    box[:, :, :4] = 0
    flown = fly_edge_pixels(depth, box, DepthArtefacts(flying_share=0.5), np.random.default_rng(1))
    moved = flown != depth
    assert moved.any()
    assert not moved[:, :, [0, 1, 2, 5, 6, 7]].any()  # only the columns on the edge
    assert ((flown[moved] > 1.0) & (flown[moved] < 3.0)).all()


def test_missing_patches_drop_samples_near_drawn_centres_only() -> None:
    rng = np.random.default_rng(2)
    exact = rng.uniform(0.0, 4.0, (20_000, 3))
    artefacts = DepthArtefacts(holes=(2, 2), hole_radius=(0.3, 0.3), hole_dropout=1.0)
    remaining = missing_patches(exact, artefacts, np.random.default_rng(3))
    dropped = exact[~remaining]
    assert 0 < len(dropped) < 0.05 * len(exact)
    # every dropped sample is within the radius of one of at most two centres
    first = dropped[0]
    near_first = np.linalg.norm(dropped - first, axis=1) <= 0.6
    rest = dropped[~near_first]
    assert len(rest) == 0 or (np.linalg.norm(rest - rest[0], axis=1) <= 0.6).all()


def test_realism_is_for_rgbd_maps_only() -> None:
    with pytest.raises(ValueError, match="RGB-D"):
        map_pair("robot", layout="office", realism="drift", size=0.03)
    with pytest.raises(ValueError, match="realism"):
        map_pair("rgbd", realism="blurry", size=0.03)
