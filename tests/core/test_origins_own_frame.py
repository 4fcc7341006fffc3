"""A moved cloud's origin from the frame where its rings are level (origins/own_frame.py)."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.datasets.lidar import lidar_pair
from app.core.origins.own_frame import resolve_moved_cloud
from app.core.registration import apply_transform


def _tilting_transform(pitch_deg: float, yaw_deg: float, shift: tuple[float, float, float]):
    pitch, yaw = np.deg2rad(pitch_deg), np.deg2rad(yaw_deg)
    about_y = np.array(
        [[np.cos(pitch), 0, np.sin(pitch)], [0, 1, 0], [-np.sin(pitch), 0, np.cos(pitch)]]
    )
    about_z = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    transform = np.eye(4)
    transform[:3, :3] = about_z @ about_y
    transform[:3, 3] = shift
    return transform


@pytest.mark.parametrize("pitch_deg", [-4.0, 3.0])
def test_a_level_frame_tilted_by_the_alignment_is_estimated_in_its_own_frame(
    pitch_deg: float,
) -> None:
    pair = lidar_pair(layout="room", change="none", angular_step_deg=1.5, random_state=41)
    transform = _tilting_transform(pitch_deg, 25.0, (3.0, -2.0, 0.5))
    resolved = resolve_moved_cloud(
        "scan", pair.reference, transform, given=None, from_file=None, estimate=True, recover=False
    )
    truth = apply_transform(pair.reference_origin[None], transform)[0]
    assert resolved.source == "estimated"
    assert np.linalg.norm(resolved.origin - truth) < 0.02


def test_a_given_origin_is_moved_by_the_alignment_and_not_estimated() -> None:
    pair = lidar_pair(layout="room", change="none", angular_step_deg=1.5, random_state=42)
    transform = _tilting_transform(3.0, -40.0, (1.0, 2.0, 0.0))
    resolved = resolve_moved_cloud(
        "scan",
        pair.reference,
        transform,
        given=pair.reference_origin[None],
        from_file=None,
        estimate=True,
        recover=False,
    )
    truth = apply_transform(pair.reference_origin[None], transform)[0]
    assert resolved.source == "given"
    np.testing.assert_allclose(resolved.origin, truth, atol=1e-9)


def test_auto_searches_no_stations_when_the_own_frame_gives_the_origin(monkeypatch) -> None:
    # a tilted single station fails the estimate once aligned: with recover_stations="auto"
    # its own frame is tried before any station search (seconds on a real frame)
    from app.core.origins import station_recovery

    def must_not_search(points, **kwargs):
        raise AssertionError("stations were searched before the own frame was tried")

    monkeypatch.setattr(station_recovery, "recover_stations", must_not_search)
    pair = lidar_pair(layout="room", change="none", angular_step_deg=1.5, random_state=41)
    transform = _tilting_transform(3.0, 25.0, (3.0, -2.0, 0.5))
    resolved = resolve_moved_cloud(
        "scan", pair.reference, transform, given=None, from_file=None, estimate=True, recover="auto"
    )
    assert resolved.source == "estimated"
