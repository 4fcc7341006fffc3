"""Edge-on faces of a change that a far station of a survey saw through (issue 29, TLS
scenes 204 and 2104).

Rules checked:

* with the other cloud's rays from several stations, edge-on candidates are changed when their
  cluster was seen through at least
  :data:`~app.core.localise.station_rays.EDGE_ON_SEEN_THROUGH_FLOOR` and far more often than
  seen as a surface, and its edge-on candidates mostly lie clear of the other cloud
  (:data:`~app.core.localise.station_rays.EDGE_ON_CLEAR_FACTOR` ``c``);
* the same cluster on a surface the other cloud has near it (sampled sparsely: TLS 2000's
  board), or one thin sheet (a rack's shelf edge grazed by every station: TLS 2004), or
  seen as a surface too, or without a survey (one station), stays unobserved.
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


def test_a_thin_sheet_seen_edge_on_clear_of_the_other_cloud_stays_unobserved():
    """TLS 2004: a rack's shelf edge, 1.26 x 0.39 m, one plane, 0.39 m from the other cloud."""
    points, status = _far_box(0)
    sheet = points[:, 2] == points[:, 2].min()
    points, status = points[sheet], status[sheet]
    assert np.count_nonzero(status == STATUS_EDGE_ON) > 20
    resolved = _resolve(points, status, np.full(len(points), 0.4))
    assert np.all(resolved[status == STATUS_EDGE_ON] == STATUS_UNOBSERVED)
