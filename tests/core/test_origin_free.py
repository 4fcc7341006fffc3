"""The origin-free test of merged surveys (``origin_free_test="surfaces"``): no origin, no stations.

Rules checked (measured numbers in bench/results/visibility.md, "Several stations per cloud"):

* a dense point in a hole of the other cloud's sampling is unchanged, also where its own
  surface ends on one side (a floor or ceiling patch against a wall);
* a point on a plane the other cloud has only on one side of it (a shadow's rim, a shadow's
  inside) is unobserved, never changed;
* a point off every plane of the other cloud (a removed box's top and side) is changed, even
  far from the other cloud's points (the coverage test called it unobserved);
* a cluster of candidates mostly on the other cloud's planes is no change;
* on a merged survey with nothing given, a removed box is found and an unchanged survey is
  quiet.
"""

from __future__ import annotations

import numpy as np
import pytest
from pykdtree.kdtree import KDTree

from app.core.datasets.lidar import lidar_pair
from app.core.datasets.scenes import _transform_points
from app.core.ground_truth import changed_iou
from app.core.labels import LABEL_CHANGED
from app.core.localise import localise_changes
from app.core.localise.origin_free import (
    behind_evidence,
    keep_evidenced_clusters,
    origin_free_status,
    settle_clusters,
)
from app.core.localise.rays import STATUS_SEEN_THROUGH, STATUS_SURFACE, STATUS_UNOBSERVED
from app.core.localise.surface import local_geometry

SPACING = 0.05


def _grid(x: tuple[float, float], y: tuple[float, float]) -> np.ndarray:
    xs = np.arange(x[0], x[1], SPACING)
    ys = np.arange(y[0], y[1], SPACING)
    return np.stack(np.meshgrid(xs, ys, indexing="ij"), -1).reshape(-1, 2)


def _floor(xy: np.ndarray, height: float = 0.0) -> np.ndarray:
    return np.column_stack([xy, np.full(len(xy), height)])


def _wall_at_x(x: float, y: tuple[float, float], z: tuple[float, float]) -> np.ndarray:
    yz = _grid(y, z)
    return np.column_stack([np.full(len(yz), x), yz])


def _box_top(centre: tuple[float, float], half: float, height: float) -> np.ndarray:
    x, y = centre
    return _floor(_grid((x - half, x + half), (y - half, y + half)), height)


def test_each_candidate_is_a_gap_a_shadow_or_a_change():
    # the room's floor ends at a wall at x = 4.  The other epoch sampled the floor with a
    # blind disc (radius 1 m around (0.5, 0)) and nothing behind an occluder for x < -2 (a
    # shadow); the own epoch has the whole floor and a box top 0.6 m up around (-1, 2.5).
    # The own floor also has a 0.6 m patch against the wall that the other did not sample.
    floor = _grid((-4.0, 4.0), (-4.0, 4.0))
    other_floor = floor[
        (np.hypot(floor[:, 0] - 0.5, floor[:, 1]) > 1.0)
        & (floor[:, 0] > -2.0)
        & ~((floor[:, 0] > 3.4) & (np.abs(floor[:, 1] + 2.5) < 0.3))
    ]
    wall = _wall_at_x(4.0, (-4.0, 4.0), (0.05, 2.0))
    other = local_geometry(np.vstack([_floor(other_floor), wall]), 10)
    own = local_geometry(np.vstack([_floor(floor), wall, _box_top((-1.0, 2.5), 0.3, 0.6)]), 10)
    candidates = np.array(
        [
            [0.5, 0.0, 0.0],  # the blind disc's centre: a sampling gap
            [3.8, -2.5, 0.0],  # the patch against the wall: a gap bounded by the wall
            [-2.2, 0.0, 0.0],  # just inside the shadow: its rim
            [-2.8, -1.0, 0.0],  # inside the shadow, 0.8 m from its rim
            [-1.0, 2.5, 0.6],  # the box top's centre, 0.6 m from the other's floor
        ]
    )
    nearest, _ = KDTree(other.points).query(candidates, k=1)
    up = np.tile([0.0, 0.0, 1.0], (len(candidates), 1))
    status = origin_free_status(candidates, up, nearest, own=own, other=other, tolerance=0.05)
    assert status.tolist() == [
        STATUS_SURFACE,
        STATUS_SURFACE,
        STATUS_UNOBSERVED,
        STATUS_UNOBSERVED,
        STATUS_SEEN_THROUGH,
    ]


def test_a_cluster_mostly_on_the_other_planes_is_no_change():
    line = np.column_stack([np.arange(20) * SPACING, np.zeros(20), np.zeros(20)])
    far = line + np.array([0.0, 5.0, 0.0])
    points = np.vstack([line, far])
    status = np.full(40, STATUS_UNOBSERVED, dtype=np.int8)
    status[:3] = STATUS_SEEN_THROUGH  # a shadow's few changed points
    status[20:] = STATUS_SEEN_THROUGH  # a change
    status[20:25] = STATUS_UNOBSERVED
    settled = settle_clusters(
        points, spacing=np.full(40, SPACING), status=status, cluster_factor=2.5
    )
    assert (settled[:20] == STATUS_UNOBSERVED).all()
    assert settled[20:].tolist() == status[20:].tolist()


def _survey(change: str, seed: int):
    pair = lidar_pair(
        layout="room",
        change=change,
        n_stations=3,
        angular_step_deg=1.5,
        misaligned=True,
        random_state=seed,
    )
    return pair, _transform_points(pair.scan, pair.true_transform)


@pytest.mark.slow
def test_a_merged_survey_without_origins_finds_a_removed_box_and_stays_quiet():
    pair, scan = _survey("removed", seed=0)
    localisation = localise_changes(pair.reference, scan, origin_free_test="surfaces")
    assert localisation.parameters["reference_visibility"] == "surfaces"
    assert changed_iou(pair, localisation) >= 0.8
    pair, scan = _survey("none", seed=0)
    quiet = localise_changes(pair.reference, scan, origin_free_test="surfaces")
    assert quiet.regions == []
    assert not (quiet.reference_label == LABEL_CHANGED).any()


def test_the_other_epochs_surface_behind_a_change_is_its_evidence():
    # a removed box's top 0.6 m over the other epoch's floor, which this epoch never saw
    top = _box_top((0.0, 0.0), 0.3, 0.6)
    floor = _floor(_grid((-1.0, 1.0), (-1.0, 1.0)))
    up = np.tile([0.0, 0.0, 1.0], (len(top), 1))
    floor_up = np.tile([0.0, 0.0, 1.0], (len(floor), 1))
    unmatched = np.ones(len(floor), dtype=bool)
    seen_only_there = behind_evidence(
        top, up, other_points=floor, other_normal=floor_up, other_unmatched=unmatched
    )
    shared = behind_evidence(
        top, up, other_points=floor, other_normal=floor_up, other_unmatched=~unmatched
    )
    # the same points standing for a wall's edge (normals across): not the surface behind
    across = behind_evidence(
        top,
        up,
        other_points=floor,
        other_normal=np.tile([1.0, 0.0, 0.0], (len(floor), 1)),
        other_unmatched=unmatched,
    )
    assert seen_only_there.all()
    assert not shared.any()
    assert not across.any()


def test_a_changed_cluster_without_evidence_is_unobserved():
    line = np.column_stack([np.arange(20) * SPACING, np.zeros(20), np.zeros(20)])
    points = np.vstack([line, line + np.array([0.0, 5.0, 0.0])])
    status = np.full(40, STATUS_SEEN_THROUGH, dtype=np.int8)
    evidence = np.zeros(40, dtype=bool)
    evidence[:5] = True  # the first cluster's top has the other's floor below it
    kept = keep_evidenced_clusters(
        points, spacing=np.full(40, SPACING), status=status, evidence=evidence, cluster_factor=2.5
    )
    assert (kept[:20] == STATUS_SEEN_THROUGH).all()
    assert (kept[20:] == STATUS_UNOBSERVED).all()


def test_a_box_seen_from_the_side_has_the_other_epochs_floor_in_its_footprint():
    # two side faces of a removed box (no top seen), 0.6 x 0.6 m, 1.2 m tall
    heights = np.arange(0.05, 1.2, SPACING)
    along = np.arange(0.0, 0.6, SPACING)
    front = np.array([[x, 0.0, z] for x in along for z in heights])
    side = np.array([[0.6, y, z] for y in along for z in heights])
    faces = np.vstack([front, side])
    status = np.full(len(faces), STATUS_SEEN_THROUGH, dtype=np.int8)
    no_evidence = np.zeros(len(faces), dtype=bool)
    spacing = np.full(len(faces), SPACING)
    under = _floor(_grid((0.0, 0.6), (0.0, 0.6)))
    beside = under + np.array([2.0, 0.0, 0.0])
    kept = keep_evidenced_clusters(
        faces,
        spacing=spacing,
        status=status,
        evidence=no_evidence,
        cluster_factor=2.5,
        floor_points=under,
    )
    dropped = keep_evidenced_clusters(
        faces,
        spacing=spacing,
        status=status,
        evidence=no_evidence,
        cluster_factor=2.5,
        floor_points=beside,
    )
    one_face = keep_evidenced_clusters(
        front,
        spacing=spacing[: len(front)],
        status=status[: len(front)],
        evidence=no_evidence[: len(front)],
        cluster_factor=2.5,
        floor_points=under,
    )
    assert (kept == STATUS_SEEN_THROUGH).all()
    assert (dropped == STATUS_UNOBSERVED).all()
    assert (one_face == STATUS_UNOBSERVED).all()  # a single face has no footprint
