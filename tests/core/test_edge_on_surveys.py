"""Edge-on faces of a change that a far station of a survey saw through (issue 29, TLS
scenes 204, 2104 and 2504).

Rules checked:

* with the other cloud's rays from several stations, edge-on candidates are changed when their
  cluster was seen through at least
  :data:`~app.core.localise.station_rays.EDGE_ON_SEEN_THROUGH_FLOOR` and far more often than
  seen as a surface, and its edge-on candidates mostly lie clear of the other cloud
  (:data:`~app.core.localise.station_rays.EDGE_ON_CLEAR_FACTOR` ``c``);
* one sheet (thinner than
  :data:`~app.core.localise.station_rays.EDGE_ON_THICKNESS_FACTOR` ``c``: a removed box's
  only sampled face, TLS 2504) needs that evidence inside its outline: seen through only
  along its rim (rays beside a grazed sheet's edge), it stays unobserved;
* the same cluster on a surface the other cloud has near it (sampled sparsely: TLS 2000's
  board), or seen as a surface too, or without a survey (one station), stays unobserved.
"""

from __future__ import annotations

import numpy as np
import pytest

from app.core.localise.rays import (
    STATUS_EDGE_ON,
    STATUS_SEEN_THROUGH,
    STATUS_SURFACE,
    STATUS_UNOBSERVED,
)
from app.core.localise.station_rays import (
    EDGE_ON_CLEAR_FACTOR,
    EDGE_ON_THICKNESS_FACTOR,
    resolve_edge_on,
)

CHANGE_THRESHOLD = 0.1
SPACING = 0.06


def _far_box(seed: int, surface_every: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A 0.5 m box's faces sampled every 6 cm (TLS 204): 80 % edge-on, 20 % seen through,
    every ``surface_every``-th seen as a surface; points (n, 3) and statuses (n,)."""
    rng = np.random.default_rng(seed)
    grid = np.arange(0.0, 0.5 + 1e-9, SPACING)
    a, b = (part.ravel() for part in np.meshgrid(grid, grid, indexing="ij"))
    faces = [
        np.column_stack([a, b, np.zeros_like(a)]),
        np.column_stack([a, b, np.full_like(a, 0.5)]),
        np.column_stack([a, np.zeros_like(a), b]),
        np.column_stack([np.zeros_like(a), a, b]),
    ]
    points = np.unique(np.round(np.vstack(faces), 6), axis=0) + rng.normal(0, 0.002, (1, 3))
    status = np.full(len(points), STATUS_EDGE_ON, dtype=np.int8)
    status[rng.permutation(len(points))[: len(points) // 5]] = STATUS_SEEN_THROUGH
    if surface_every:
        status[::surface_every] = STATUS_SURFACE
    return points, status


def _resolve(points, status, surface_distance):
    clear = surface_distance >= EDGE_ON_CLEAR_FACTOR * CHANGE_THRESHOLD
    return resolve_edge_on(
        points,
        spacing=np.full(len(points), SPACING),
        status=status,
        cluster_factor=2.5,
        clear_of_other=clear,
        min_thickness=EDGE_ON_THICKNESS_FACTOR * CHANGE_THRESHOLD,
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_far_stations_edge_on_box_clear_of_the_other_cloud_is_changed(seed):
    points, status = _far_box(seed)
    edge_on = status == STATUS_EDGE_ON
    resolved = _resolve(points, status, np.full(len(points), 0.4))
    assert np.all(resolved[edge_on] == STATUS_SEEN_THROUGH)
    assert np.all(resolved[~edge_on] == status[~edge_on])
    # without a survey (no clear_of_other), only the seen-through share decides: 20 % < 50 %
    alone = resolve_edge_on(
        points, spacing=np.full(len(points), SPACING), status=status, cluster_factor=2.5
    )
    assert np.all(alone[edge_on] == STATUS_UNOBSERVED)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_an_edge_on_surface_the_other_cloud_has_near_it_stays_unobserved(seed):
    """TLS 2000: the reference's board, 0.17 m from the scan's sparse samples of it."""
    points, status = _far_box(seed)
    resolved = _resolve(points, status, np.full(len(points), 0.17))
    assert np.all(resolved[status == STATUS_EDGE_ON] == STATUS_UNOBSERVED)


def test_an_edge_on_cluster_also_seen_as_a_surface_stays_unobserved():
    points, status = _far_box(0, surface_every=4)
    resolved = _resolve(points, status, np.full(len(points), 0.4))
    assert np.all(resolved[status == STATUS_EDGE_ON] == STATUS_UNOBSERVED)


def _sheet(seed: int, spacing: float, size: tuple[float, float]) -> np.ndarray:
    """One level sheet (a box's only sampled face) sampled every ``spacing``; points (n, 3)."""
    rng = np.random.default_rng(seed)
    a, b = np.meshgrid(
        np.arange(0.0, size[0] + 1e-9, spacing), np.arange(0.0, size[1] + 1e-9, spacing)
    )
    points = np.column_stack([a.ravel(), b.ravel(), np.zeros(a.size)])
    return points + rng.normal(0, 0.002, points.shape)


def _resolve_sheet(points, status, spacing):
    return resolve_edge_on(
        points,
        spacing=np.full(len(points), spacing),
        status=status,
        cluster_factor=2.5,
        clear_of_other=np.ones(len(points), dtype=bool),
        min_thickness=EDGE_ON_THICKNESS_FACTOR * CHANGE_THRESHOLD,
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_sheet_seen_through_only_along_its_rim_stays_unobserved(seed):
    """A thin sheet grazed by a station (a rack's shelf edge, 0.5 x 0.5 m at 6 cm): rays
    beside its rim cross its plane just past its last points; its interior is all edge-on."""
    points = _sheet(seed, SPACING, (0.5, 0.5))
    rim = (
        np.minimum.reduce([points[:, 0], 0.5 - points[:, 0], points[:, 1], 0.5 - points[:, 1]])
        < 0.5 * SPACING
    )
    status = np.where(rim, STATUS_SEEN_THROUGH, STATUS_EDGE_ON).astype(np.int8)
    assert 0.3 < rim.mean() < 0.5  # far above the floor: only where they lie decides
    resolved = _resolve_sheet(points, status, SPACING)
    assert np.all(resolved[~rim] == STATUS_UNOBSERVED)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("pattern", ["scattered", "one quarter"])
def test_a_removed_boxs_one_face_seen_through_inside_its_outline_is_changed(seed, pattern):
    """TLS 2504: the reference saw only the box's top (0.7 x 0.5 m at 1.6 cm, 12 mm thick); the
    one scan station reaching it grazes it at 85 deg: 28 % seen through, the rest edge-on,
    0.4 m from the scan's cloud.  Main's single-sheet guard left it unobserved (recall 25 %)."""
    spacing = 0.016
    points = _sheet(seed, spacing, (0.7, 0.5))
    rng = np.random.default_rng(seed)
    if pattern == "scattered":
        through = rng.random(len(points)) < 0.28
    else:
        through = (points[:, 0] < 0.35) & (points[:, 1] < 0.25)
    status = np.where(through, STATUS_SEEN_THROUGH, STATUS_EDGE_ON).astype(np.int8)
    resolved = _resolve_sheet(points, status, spacing)
    assert np.all(resolved == STATUS_SEEN_THROUGH)
    # the same sheet seen through only along its rim stays unobserved
    rim = (
        np.minimum.reduce([points[:, 0], 0.7 - points[:, 0], points[:, 1], 0.5 - points[:, 1]])
        < spacing
    )
    status = np.where(rim, STATUS_SEEN_THROUGH, STATUS_EDGE_ON).astype(np.int8)
    assert rim.mean() > 0.1
    assert np.all(_resolve_sheet(points, status, spacing)[~rim] == STATUS_UNOBSERVED)


def test_the_edge_on_clusters_are_found_on_the_ray_tests_threads(monkeypatch):
    """The clusters of the edge-on and seen-through candidates (3,362 of the scan's 113,717
    candidates edge-on on the 1M held-out pair) are linked on the ray test's threads: the same
    statuses as on one."""
    from app.core.localise import station_rays

    points, status = _far_box(0)
    one = resolve_edge_on(
        points, spacing=np.full(len(points), SPACING), status=status, cluster_factor=2.5
    )
    used: list[int] = []
    cluster_labels = station_rays.cluster_labels

    def recorded(points, radius, threads=1):
        used.append(threads)
        return cluster_labels(points, radius, threads)

    monkeypatch.setattr(station_rays, "cluster_labels", recorded)
    two = resolve_edge_on(
        points, spacing=np.full(len(points), SPACING), status=status, cluster_factor=2.5, threads=2
    )
    np.testing.assert_array_equal(two, one)
    assert used == [2]
