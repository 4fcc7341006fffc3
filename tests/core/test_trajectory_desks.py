"""The trajectory test on a desk at the sensors' height (issue 29): a box removed from a desk
takes neither the desk's underside nor the band of the box's foot over the desk top with it.

Both epochs are swept corridors with their trajectories (``tests.helpers.trajectory_scenes``),
16-ring-like (rings 2 degrees apart, none level).  A desk slab stands 1-2 cm above the
reference's sensor, which samples its underside from below; the scan's sensor is 3-6 cm lower
and its underside samples end 0.3-0.5 m round the box's footprint (the gap a sparse map
leaves).  Neither epoch samples the desk top.  The reference holds a box on the desk; the scan
lost it.  The scan's rays see through the box's place, foot included, and meet the desk's
underside only edge-on; truth calls the underside unchanged and the foot too (within 10 cm of
the desk top that is still there).
"""

from __future__ import annotations

import numpy as np
import pytest

from app.core.labels import LABEL_CHANGED
from app.core.pipeline import compare
from tests.helpers.trajectory_scenes import OFFSET, in_box, swept_map, without_band_round_box

DESK = (np.array([3.0, 2.9, 0.72]), np.array([4.8, 3.8, 0.75]))
BOX = (np.array([3.6, 3.2, 0.75]), np.array([4.1, 3.7, 1.25]))


@pytest.fixture(scope="module", params=[0, 1, 2])
def removed_from_desk(request: pytest.FixtureRequest):
    seed = request.param
    rng = np.random.default_rng(seed)
    path_x = np.arange(1.0, 10.01, 0.5) + rng.uniform(-0.2, 0.2)
    reference_height = DESK[0][2] - rng.uniform(0.01, 0.02)
    scan_height = DESK[0][2] - rng.uniform(0.03, 0.06)
    reference_path = np.column_stack(
        [path_x, np.full(path_x.size, 2.5), np.full(path_x.size, reference_height)]
    )
    scan_path = np.column_stack(
        [path_x + 0.25, np.full(path_x.size, 2.3), np.full(path_x.size, scan_height)]
    )
    rings = {"step_deg": 2.0, "azimuth_step_deg": 0.5}
    reference = swept_map([DESK, BOX], reference_path, seed=10 + seed, **rings)
    scan = swept_map([DESK], scan_path, seed=20 + seed, start_time=5000.0, **rings)
    scan_cloud = without_band_round_box(
        scan.cloud, BOX, rng.uniform(0.3, 0.5), (DESK[0][2] - 0.01, DESK[0][2] + 0.01)
    )
    result = compare(reference.cloud, scan_cloud, threads=1)
    return reference, result


def test_a_box_removed_from_a_desk_leaves_the_desk_underside_and_its_foot_unchanged(
    removed_from_desk,
) -> None:
    reference, result = removed_from_desk
    points = np.asarray(reference.cloud.points) - OFFSET
    changed = result.reference_label == LABEL_CHANGED
    underside = in_box(reference.cloud.points, DESK) & (points[:, 2] < DESK[0][2] + 0.005)
    on_box = in_box(reference.cloud.points, BOX)
    foot = on_box & (points[:, 2] < BOX[0][2] + 0.07)
    body = on_box & (points[:, 2] > BOX[0][2] + 0.15)

    assert result.visibility["reference"].test == "trajectory"
    assert np.mean(changed[body]) >= 0.95
    # on main 42-118 underside points (32-53 %) were promoted through the box's faces and
    # 19-68 foot points (31-94 %) were seen through
    assert np.mean(changed[underside]) <= 0.05, np.count_nonzero(changed[underside])
    assert np.mean(changed[foot]) <= 0.15, np.count_nonzero(changed[foot])
    assert result.localisation["reference_candidates_undersides_edge_on"] > 0
    assert result.localisation["reference_candidates_resting_on_unseen_support"] > 0
