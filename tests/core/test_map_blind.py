"""The map test's blind areas (issue 29): a desk the scan's path never looked at, standing in
a corner the scan never filmed, is a coverage difference even though the scan saw the floor
under it and one end of it; the same desk removed, with the corner seen, is still removed."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.labels import LABEL_CHANGED
from app.core.localise import localise_changes
from app.core.localise.map_blind import blind_clusters, held_by_isolated
from app.core.localise.surface import local_geometry
from tests.helpers.fused_rooms import box_sides, plane

SPACING = 0.02
DESK_LOW, DESK_HIGH = np.array([0.2, 1.55, 0.0]), np.array([1.5, 2.3, 0.75])
LEG = 0.05


def _desk(rng, *, near_end_only=False):
    """A desk in the corner at x = 0, y = 2.5 (four legs, a 3 cm top) with a box on it; with
    ``near_end_only`` just the lower 0.6 m of its two legs at high x (all a camera filming the
    floor under it from that end saw)."""
    legs = []
    for x in (DESK_LOW[0], DESK_HIGH[0] - LEG):
        for y in (DESK_LOW[1], DESK_HIGH[1] - LEG):
            leg_top = 0.6 if near_end_only else DESK_HIGH[2] - 0.03
            if near_end_only and x < 1.0:
                continue
            legs.append(box_sides(rng, [x, y, 0.0], [x + LEG, y + LEG, leg_top], "nsew", SPACING))
    if near_end_only:
        return np.vstack(legs)
    top = box_sides(rng, [*DESK_LOW[:2], 0.72], DESK_HIGH, spacing=SPACING)
    box = box_sides(rng, [0.3, 1.6, 0.75], [0.8, 2.25, 1.25], spacing=SPACING)
    return np.vstack([*legs, top, box])


def _room(rng, *, corner_seen):
    """A 3 x 2.5 m floor (all of it, under the desk too), the wall at y = 2.5 and the wall at
    x = 0, up to 2.4 m; without ``corner_seen`` the walls' corner is seen above 1.6 m only
    (a path that filmed the floor and the rest of the room, never the desk's corner)."""
    floor = plane(rng, [0, 0, 0], [3.0, 0, 0], [0, 2.5, 0], spacing=SPACING)
    if corner_seen:
        walls = [
            plane(rng, [0, 2.5, 0], [3.0, 0, 0], [0, 0, 2.4], spacing=SPACING),
            plane(rng, [0, 0, 0], [0, 2.5, 0], [0, 0, 2.4], spacing=SPACING),
        ]
    else:
        walls = [
            plane(rng, [1.9, 2.5, 0], [1.1, 0, 0], [0, 0, 2.4], spacing=SPACING),
            plane(rng, [0, 2.5, 1.6], [1.9, 0, 0], [0, 0, 0.8], spacing=SPACING),
            plane(rng, [0, 0, 0], [0, 1.4, 0], [0, 0, 2.4], spacing=SPACING),
            plane(rng, [0, 1.4, 1.6], [0, 1.1, 0], [0, 0, 0.8], spacing=SPACING),
        ]
    return np.vstack([floor, *walls])


@pytest.mark.parametrize("seed", range(2))
def test_a_desk_in_a_corner_the_scan_never_filmed_is_no_change(seed):
    """Main called the desk removed (its top has the floor the scan saw beneath it, its sides
    meet nothing and fall to the default): about 6,950 of its 7,615 points in one region."""
    rng = np.random.default_rng(seed)
    desk = _desk(rng)
    reference = np.vstack([_room(rng, corner_seen=True), desk])
    scan = np.vstack([_room(rng, corner_seen=False), _desk(rng, near_end_only=True)])
    found = localise_changes(reference, scan, threads=1)
    assert np.count_nonzero(found.reference_label == LABEL_CHANGED) == 0
    assert found.regions == []


@pytest.mark.parametrize("seed", range(2))
def test_the_same_desk_removed_with_its_corner_seen_is_found(seed):
    rng = np.random.default_rng(seed)
    desk = _desk(rng)
    desk = desk[desk[:, 2] > 0.12]  # its feet are within the change threshold of the floor
    reference = np.vstack([_room(rng, corner_seen=True), desk])
    scan = _room(rng, corner_seen=True)
    found = localise_changes(reference, scan, threads=1)
    on_desk = found.reference_label[-desk.shape[0] :] == LABEL_CHANGED
    assert on_desk.mean() >= 0.9


def test_a_cluster_ringed_by_coverage_differences_is_blind_and_one_ringed_by_matches_is_not():
    """Two changed clusters: one whose shell is another cluster's coverage difference, one
    whose shell is this epoch's matched points."""
    rng = np.random.default_rng(0)
    wall = plane(rng, [0, 0, 0], [1.0, 0, 0], [0, 0, 1.0], spacing=SPACING)
    panel = wall[::2] - np.array([0.0, 0.15, 0.0])  # 15 cm in front of the wall
    beside = np.array([3.0, 0.0, 0.0])
    points = np.vstack([panel, wall, panel + beside, wall + beside])
    n_panel, n_wall = panel.shape[0], wall.shape[0]
    # candidates: the first panel, the wall behind it (a coverage difference), the second
    # panel; the wall behind the second is matched
    index = np.r_[np.arange(n_panel + n_wall), np.arange(n_panel) + n_panel + n_wall]
    labels = np.r_[np.zeros(n_panel), np.ones(n_wall), np.full(n_panel, 2)].astype(np.int64)
    coverage = np.array([False, True, False])
    radius = np.full(index.shape[0], 3 * SPACING)
    blind, share = blind_clusters(points, index, radius, labels, coverage, 0.1)
    assert blind.tolist() == [True, False, False]
    assert share[0] > 0.9 and share[2] == 0.0


def _panel_before_wall() -> tuple[np.ndarray, ...]:
    """A panel 0.15 m before a wall (cluster 0) and the wall (cluster 1, a coverage
    difference): points (n, 3), their index (n,), cluster labels (n,), each cluster's coverage
    flag (2,) and the search radius (n,)."""
    rng = np.random.default_rng(0)
    wall = plane(rng, [0, 0, 0], [1.0, 0, 0], [0, 0, 1.0], spacing=SPACING)
    panel = wall[::2] - np.array([0.0, 0.15, 0.0])
    points = np.vstack([panel, wall])
    index = np.arange(points.shape[0])
    labels = np.r_[np.zeros(panel.shape[0]), np.ones(wall.shape[0])].astype(np.int64)
    coverage = np.array([False, True])
    return points, index, labels, coverage, np.full(index.shape[0], 3 * SPACING)


def test_a_cluster_ringed_by_coverage_differences_is_not_blind_where_the_other_epoch_saw_round_it():
    """The panel of the test above, with the other epoch's surface carrying on past its
    border (a removed board high on a wall, the ceiling over it seen by the other path, the
    wall round it not: RGB-D room 700 with metric normals, 100 % -> 0 % without this)."""
    points, index, labels, coverage, radius = _panel_before_wall()
    seen_around = np.array([True, False])
    blind, _ = blind_clusters(points, index, radius, labels, coverage, 0.1, seen_around)
    assert blind.tolist() == [False, False]
    blind, _ = blind_clusters(points, index, radius, labels, coverage, 0.1)
    assert blind.tolist() == [True, False]


def test_a_cluster_ringed_by_an_unseen_face_is_not_blind():
    """The panel of the first ringed test, its shell an unseen face (a coverage difference as
    a face of an object the other epoch saw the other faces of): the other epoch looked there.
    A box turned in place has its new face where the old box stood as an unseen face, and the
    rest of the turned box beside it was blind on that face alone (held-out robot 2604: the
    scan's turned box 76 -> 97 % with this)."""
    points, index, labels, coverage, radius = _panel_before_wall()
    faces = np.array([False, True])
    blind, share = blind_clusters(points, index, radius, labels, coverage, 0.1, faces=faces)
    assert blind.tolist() == [False, False]
    assert share[0] == 0.0
    blind, _ = blind_clusters(points, index, radius, labels, coverage, 0.1, faces=~faces)
    assert blind.tolist() == [True, False]


def test_a_change_joined_to_coverage_differences_is_judged_on_its_own_shell():
    """A panel 5 cm before a wall patch that is a coverage difference, the two joined into
    one cluster of candidates, the wall carrying on matched beyond the patch: the panel's
    surroundings are the patch, so it is blind.  Main took the panel and the patch for one
    cluster and its shell for the matched wall beyond: not blind (held-out RGB-D room 1904's
    cabinet in a corner neither the scan's path filmed, joined through the back wall's
    coverage difference to a wall band 1.5 m away: 1,338 false changed points)."""
    rng = np.random.default_rng(0)
    patch = plane(rng, [0, 0, 0], [1.0, 0, 0], [0, 0, 1.0], spacing=SPACING)
    beyond = plane(rng, [1.0, 0, 0], [1.0, 0, 0], [0, 0, 1.0], spacing=SPACING)
    panel = plane(rng, [0.3, -0.05, 0.3], [0.4, 0, 0], [0, 0, 0.4], spacing=SPACING)
    points = np.vstack([panel, patch, beyond])
    n_candidates = panel.shape[0] + patch.shape[0]
    index = np.arange(n_candidates)
    labels = np.r_[np.zeros(panel.shape[0]), np.ones(patch.shape[0])].astype(np.int64)
    coverage = np.array([False, True])
    radius = np.full(n_candidates, 3.5 * SPACING)
    blind, share = blind_clusters(points, index, radius, labels, coverage, 0.1)
    assert blind.tolist() == [True, False]
    assert share[0] > 0.9


def _panel_before_a_held_backing(rng, holders: str) -> tuple[np.ndarray, ...]:
    """A panel (the only candidates, a change part) 15 cm before a backing wall this epoch
    matched, and the other epoch there: a wall 12 cm behind the backing and, with ``holders``
    "flying", a grid of lone samples (12 cm apart) 2 cm behind the backing and 10 cm before
    that wall, within the change threshold of the backing (a fused map's flying pixels in front
    of a far wall, their neighbours its samples); with "surface", a wall 2 cm behind the
    backing instead.  Returns this epoch's points, the candidates' index, labels, coverage,
    radius and the other epoch's geometry."""
    panel = plane(rng, [0.2, 0.0, 0.2], [0.4, 0, 0], [0, 0, 0.6], spacing=SPACING)
    backing = plane(rng, [0.0, 0.15, 0.2], [0.8, 0, 0], [0, 0, 0.8], spacing=SPACING)
    far = plane(rng, [-0.2, 0.27, 0.0], [1.2, 0, 0], [0, 0, 1.2], spacing=SPACING)
    if holders == "flying":
        x, z = np.meshgrid(np.arange(0.02, 0.8, 0.12), np.arange(0.22, 1.0, 0.12))
        lone = np.column_stack([x.ravel(), np.full(x.size, 0.17), z.ravel()])
        other = np.vstack([far, lone])
    else:
        other = np.vstack([far, far - np.array([0.0, 0.1, 0.0])])
    points = np.vstack([panel, backing])
    index = np.arange(panel.shape[0])
    labels = np.zeros(panel.shape[0], dtype=np.int64)
    radius = np.full(panel.shape[0], 3 * SPACING)
    return points, index, labels, np.array([False]), radius, local_geometry(other, 10)


def test_a_shell_the_other_epoch_holds_only_by_lone_samples_is_unseen():
    """The panel's shell (the backing) is matched only through the other epoch's lone samples
    in the air: no evidence that the other path saw the place, so the panel is blind; main
    counted them as sight (not blind: drifting RGB-D rooms' flying pixels held a wall round a
    change).  Held by the other epoch's surface, it stays seen."""
    rng = np.random.default_rng(0)
    points, index, labels, coverage, radius, other = _panel_before_a_held_backing(rng, "flying")
    backing = points[index.shape[0] :]
    assert held_by_isolated(backing, other, 0.1).mean() > 0.9
    assert blind_clusters(points, index, radius, labels, coverage, 0.1)[0].tolist() == [False]
    blind, share = blind_clusters(points, index, radius, labels, coverage, 0.1, other=other)
    assert blind.tolist() == [True] and share[0] > 0.9
    points, index, labels, coverage, radius, other = _panel_before_a_held_backing(rng, "surface")
    assert not held_by_isolated(points[index.shape[0] :], other, 0.1).any()
    blind, share = blind_clusters(points, index, radius, labels, coverage, 0.1, other=other)
    assert blind.tolist() == [False] and share[0] == 0.0
