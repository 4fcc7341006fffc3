"""The trajectory test tries the poses that had a candidate in view, not only the nearest ones.

A 16-ring lidar sees +-15 degrees about level: from a sensor 1.7 m over the floor, a chair's
seat (0.44 m) is in view only from 4.6 m away or more.  Neither the nearest poses nor those
whose floor returns lie nearest the seat (their rays reach the floor past the chair's place,
not through it) have a ray through the seat; the poses a few metres along the path do
(:func:`~app.core.localise.trajectory_visibility.group_views`).  Rules checked: a chair
removed from an office mapped by such a robot, with its trajectory, is ``removed`` nearly
whole (before: a quarter of it ``unobserved``); each pose's view spans its returns.
"""

from __future__ import annotations

import numpy as np
import pytest

from app.core.datasets.maps import map_pair
from app.core.labels import LABEL_CHANGED
from app.core.localise.trajectory_visibility import group_views
from app.core.pipeline import compare


def test_a_removed_chair_seen_only_from_afar_is_removed() -> None:
    # robot scene 2302 of bench.moving_maps: an office, misaligned, one chair removed
    pair = map_pair("robot", layout="office", change="mixed", misaligned=True, random_state=2302)
    reference, scan = pair.clouds(with_trajectory=True)
    (removed,) = [number for number, change in enumerate(pair.changes) if change.kind == "removed"]

    result = compare(reference, scan, threads=1)

    truly = (pair.reference_change == removed) & pair.reference_changed & pair.reference_scored
    found = (result.reference_label[truly] == LABEL_CHANGED).mean()
    assert found >= 0.95, found
    assert result.visibility["reference"].test == "trajectory"


def test_each_pose_views_its_returns_span() -> None:
    origins = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    points = np.array(
        [[5.0, 0.0, -1.0], [5.0, 0.0, 1.0], [0.0, 5.0, 0.0], [13.0, 0.0, 4.0], [14.0, 0.0, 0.0]]
    )

    views = group_views(points, origins, (np.arange(5), np.array([0, 3, 5])))

    np.testing.assert_allclose(views.lowest, [-1 / np.sqrt(26), 0.0])
    np.testing.assert_allclose(views.highest, [1 / np.sqrt(26), 0.8])
    np.testing.assert_allclose(views.reach, [np.sqrt(26), 5.0])
    assert views.cone_cosine[1] == pytest.approx(2 / np.sqrt(5))
