"""The trajectory visibility test, end to end through ``compare`` on a swept corridor.

Rules checked (both epochs are merged, voxel-thinned sweeps along different paths, with their
trajectories): a box removed where the scan's path saw the floor and wall behind it is mostly
``removed``; a box behind a partition that the scan's path never saw is ``unobserved``, not
removed; nothing else is called changed; the result says the trajectory test was used and
reports each trajectory (poses, time span, points outside it).  With per-point times and
without them (line-of-sight poses).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from app.core.labels import LABEL_CHANGED, LABEL_UNOBSERVED
from app.core.pipeline import compare
from tests.helpers.trajectory_scenes import HIDDEN_BOX, SEEN_BOX, corridor_pair, in_box


@pytest.fixture(scope="module", params=[True, False], ids=["times", "line-of-sight"])
def compared(request: pytest.FixtureRequest):
    reference, scan = corridor_pair(with_times=request.param)
    return reference, scan, compare(reference.cloud, scan.cloud, threads=1), request.param


def test_a_removed_box_whose_place_the_other_path_saw_is_removed(compared) -> None:
    reference, _, result, with_times = compared
    on_box = in_box(reference.cloud.points, SEEN_BOX)

    changed = (result.reference_label[on_box] == LABEL_CHANGED).mean()

    assert changed >= (0.85 if with_times else 0.75), changed
    assert any(region.kind == "removed" for region in result.regions)


def test_a_box_the_other_path_never_saw_is_unobserved(compared) -> None:
    reference, _, result, _ = compared
    hidden = in_box(reference.cloud.points, HIDDEN_BOX)

    assert (result.reference_label[hidden] == LABEL_UNOBSERVED).mean() >= 0.95
    assert not (result.reference_label[hidden] == LABEL_CHANGED).any()


def test_nothing_else_is_changed(compared) -> None:
    reference, _, result, _ = compared
    elsewhere = ~(
        in_box(reference.cloud.points, SEEN_BOX) | in_box(reference.cloud.points, HIDDEN_BOX)
    )

    assert (result.reference_label[elsewhere] == LABEL_CHANGED).sum() <= 0.001 * elsewhere.sum()
    assert (result.scan_label == LABEL_CHANGED).sum() == 0


def test_the_result_reports_the_trajectory_test_and_each_trajectory(compared) -> None:
    reference, scan, result, with_times = compared

    for side, cloud in (("reference", reference), ("scan", scan)):
        assert result.visibility[side].origins == "trajectory"
        (origin,) = result.sensor_origins[side]
        assert origin.source == "trajectory"
        entry = origin.trajectory
        assert entry["poses"] == len(cloud.trajectory)
        assert entry["time_span"] == [cloud.trajectory.times[0], cloud.trajectory.times[-1]]
        assert entry["points_outside"] == 0
        assert entry["assignment"] == ("times" if with_times else "line_of_sight")
        np.testing.assert_allclose(entry["path"][0], cloud.trajectory.positions[0])
    assert result.visibility["scan"].test == "trajectory"  # the scan's candidates
    assert result.visibility["reference"].test == "trajectory"


def test_points_outside_the_trajectory_times_are_counted() -> None:
    reference, scan = corridor_pair()
    trajectory = scan.trajectory
    shortened = dataclasses.replace(
        trajectory, times=trajectory.times[:-4], positions=trajectory.positions[:-4]
    )
    times = scan.cloud.attributes["time"]
    # the last two sweeps lie 0.9 s and more beyond the end: outside the tolerance (0.1 s,
    # the median pose step)
    beyond = int((times > shortened.times[-1] + 0.5).sum())

    result = compare(
        reference.cloud, dataclasses.replace(scan.cloud, trajectory=shortened), threads=1
    )

    assert beyond > 0
    assert result.sensor_origins["scan"][0].trajectory["points_outside"] == beyond
