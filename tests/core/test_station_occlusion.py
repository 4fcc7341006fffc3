"""Returns given to a station that could not have seen them (issue 29, TLS scene 2104).

Rules checked:

* returns denser in direction than their station samples (a clump of another station's
  returns taken beside it) go to a station that could see them; a station's own lattice stays.

* a return assigned to a station whose own returns all lie in front of it in its direction
  (a single-return lidar has one return a ray) goes to a station that could see it; a true
  return just past the station's silhouette edge stays (its neighbours on its own surface);
* a whole clump of another station's returns behind a station's own surface (each one's nearest
  directions among the station's returns are the clump's own) goes, together, to the station
  that saw it (TLS 2004);
* so does a clump denser in direction than the station's rays where the station's own returns
  in front of it were given to another station (they cover nothing then): a station samples
  each direction once;
* the one direction query a station's own tests share finds, for the clump test, the same
  neighbours within the cover distance as a query bounded by it (dense returns, with more of
  them than that query holds, queried again), and the same hidden returns as
  ``hidden_from``'s own query.
"""

from __future__ import annotations

import numpy as np

from app.core.localise.station_occlusion import (
    CLUMP_COVER_STEPS,
    CLUMP_DENSE_STEPS,
    CLUMP_NEIGHBOURS,
    NEIGHBOURS,
    _cover_neighbours,
    hidden_from,
    own_tests,
    reassign_hidden_returns,
    station_view,
)

NEAR = np.array([0.0, 0.0, 1.0])
"""Station 0: sees a wall x = 5 (for y < 1.5) and, past its edge, a wall x = 8."""
FAR = np.array([6.0, 4.0, 1.0])
"""Station 1: sees the wall x = 8 from 2 m."""


def _hits(origin: np.ndarray, plane_x: float, step_deg: float) -> np.ndarray:
    """Where a lidar at ``origin`` with a ``step_deg`` lattice of rays meets the plane
    x = ``plane_x``, rays within 30 degrees of +x, shape (m, 3)."""
    angles = np.radians(np.arange(-30.0, 30.0 + 1e-9, step_deg))
    yaw, pitch = np.meshgrid(angles, angles, indexing="ij")
    direction = np.stack(
        [np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)], axis=-1
    ).reshape(-1, 3)
    return origin + ((plane_x - origin[0]) / direction[:, :1]) * direction


def _survey() -> tuple[np.ndarray, np.ndarray]:
    """The two stations' returns and their true station, shapes (n, 3) and (n,)."""
    near_wall = _hits(NEAR, 5.0, 1.0)
    past_edge = near_wall[:, 1] >= 1.5
    near = np.where(past_edge[:, None], _hits(NEAR, 8.0, 1.0), near_wall)
    far = _hits(FAR, 8.0, 3.0)
    points = np.vstack([near, far])
    return points, np.repeat([0, 1], [len(near), len(far)])


def test_a_return_behind_its_stations_own_surface_goes_to_the_station_that_saw_it():
    points, truth = _survey()
    origins = np.vstack([NEAR, FAR])
    behind_near_wall = (truth == 1) & (points[:, 1] < 1.0)  # station 0 sees x = 5 there
    assigned = truth.copy()
    wrong = np.flatnonzero(behind_near_wall)[::3]
    assigned[wrong] = 0
    station = reassign_hidden_returns(points, origins, assigned)
    np.testing.assert_array_equal(station[wrong], 1)
    # every other return keeps its station, station 0's returns past its wall's edge included
    others = np.setdiff1d(np.arange(len(points)), wrong)
    np.testing.assert_array_equal(station[others], truth[others])
    assert np.count_nonzero((truth == 0) & (points[:, 0] > 7.0)) > 50


FAR_AWAY = np.array([20.0, 0.0, 1.0])
"""Station 2: 20 m from station 0, a wall x = 18.5 beside it and one x = 25 ahead."""


def test_a_clump_denser_than_its_station_samples_goes_to_the_station_beside_it():
    # a merged survey's returns lie a few centimetres apart next to the station that took
    # them; given to station 0, 18 m away, they are a clump behind its wall x = 5 whose
    # members are each other's nearest directions (so none is hidden by the test above), far
    # denser than station 0's 1 degree step (TLS 2005, 2305)
    points, truth = _survey()
    beside = _hits(FAR_AWAY, FAR_AWAY[0] - 1.5, 1.0)  # on its -x side, 2.6 cm apart
    beside = beside[np.all(np.abs(beside[:, 1:] - FAR_AWAY[1:]) < 0.3, axis=1)]
    ahead = _hits(FAR_AWAY, FAR_AWAY[0] + 5.0, 1.0)
    points = np.vstack([points, ahead, beside])
    truth = np.concatenate([truth, np.full(len(ahead) + len(beside), 2)])
    origins = np.vstack([NEAR, FAR, FAR_AWAY])
    assigned = truth.copy()
    clump = np.arange(len(truth) - len(beside), len(truth))
    assigned[clump] = 0
    station = reassign_hidden_returns(points, origins, assigned)
    np.testing.assert_array_equal(station[clump], 2)
    others = np.setdiff1d(np.arange(len(points)), clump)
    np.testing.assert_array_equal(station[others], truth[others])


BEHIND = np.array([6.0, 0.0, 1.0])
"""Station 1 of the clump tests: sees the wall x = 8 from 2 m, behind station 0's wall x = 5."""


def _survey_behind() -> tuple[np.ndarray, np.ndarray]:
    """Station 0's returns (as in :func:`_survey`) and station 1's from :data:`BEHIND`, and
    their true station, shapes (n, 3) and (n,)."""
    near = _survey()[0][: len(_hits(NEAR, 5.0, 1.0))]
    behind = _hits(BEHIND, 8.0, 3.0)
    return np.vstack([near, behind]), np.repeat([0, 1], [len(near), len(behind)])


def _behind_near_wall(points: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Station 1's returns on the wall x = 8 in a patch where station 0 saw only its wall
    x = 5 in front of them, shape (n,), bool."""
    patch = (np.abs(points[:, 1]) < 0.6) & (np.abs(points[:, 2] - 1.0) < 0.6)
    return (truth == 1) & patch


def test_a_clump_behind_its_stations_own_surface_goes_together_to_the_station_that_saw_it():
    points, truth = _survey_behind()
    origins = np.vstack([NEAR, BEHIND])
    clump = np.flatnonzero(_behind_near_wall(points, truth))
    assigned = truth.copy()
    assigned[clump] = 0  # every return of the patch: each one's neighbours are the clump's
    station = reassign_hidden_returns(points, origins, assigned)
    assert clump.size >= 20
    np.testing.assert_array_equal(station[clump], 1)
    others = np.setdiff1d(np.arange(len(points)), clump)
    np.testing.assert_array_equal(station[others], truth[others])


def test_a_clump_denser_than_its_stations_rays_goes_to_the_station_that_took_it():
    points, truth = _survey_behind()
    # a third station 0.5 m from the wall x = 8 samples it densely; a patch of its returns is
    # given to station 0
    close = np.array([7.5, 0.0, 1.0])
    dense = _hits(close, 8.0, 1.0)
    points = np.vstack([points, dense])
    truth = np.concatenate([truth, np.full(len(dense), 2)])
    patch = (truth == 2) & (np.abs(points[:, 1]) < 0.15) & (np.abs(points[:, 2] - 1.0) < 0.15)
    origins = np.vstack([NEAR, BEHIND, close])
    direction = (points[patch] - NEAR).mean(axis=0)
    direction /= np.linalg.norm(direction)
    # station 0's own returns in front of the patch were given to station 1: nothing covers it
    seen = (points - NEAR) / np.linalg.norm(points - NEAR, axis=1)[:, None]
    in_front = (truth == 0) & (seen @ direction > np.cos(np.radians(4.0)))
    assigned = truth.copy()
    assigned[in_front] = 1
    assigned[patch] = 0
    # as seen from station 0 (1 degree steps) the patch's returns are far closer than a step
    gap = np.degrees(np.radians(1.0) * 0.5 / np.linalg.norm(points[patch] - NEAR, axis=1).min())
    assert np.count_nonzero(patch) >= 20 and gap < CLUMP_DENSE_STEPS
    station = reassign_hidden_returns(points, origins, assigned)
    np.testing.assert_array_equal(station[patch], 2)


def test_the_shared_direction_query_finds_what_each_tests_own_query_finds():
    points, _ = _survey_behind()
    close = np.array([7.5, 0.0, 1.0])
    dense = _hits(close, 8.0, 1.0)  # far denser than station 0's step, as seen from it
    returns = np.vstack([points, dense[np.abs(dense[:, 1]) < 0.3]])
    view = station_view(returns, NEAR)
    squared, index = view.tree.query(view.directions, k=NEIGHBOURS + 1, sqr_dists=True)
    near, near_index = _cover_neighbours(view, squared, np.sqrt(squared), index)
    bound = CLUMP_COVER_STEPS * view.step
    expected, expected_index = view.tree.query(
        view.directions, k=CLUMP_NEIGHBOURS + 1, distance_upper_bound=bound
    )
    queried_again = squared[:, -1] < bound * bound
    assert queried_again.any() and not queried_again.all()
    np.testing.assert_array_equal(near, expected[:, 1:])
    found = np.isfinite(near)
    np.testing.assert_array_equal(near_index[found], expected_index[:, 1:][found])
    hidden, _ = own_tests(returns, NEAR, view)
    np.testing.assert_array_equal(hidden, hidden_from(returns, NEAR, returns, among_returns=True))
