"""The trajectory visibility test: what the other epoch's moving sensor saw at each candidate.

A cloud taken along a trajectory is cut into pseudo-stations (:mod:`app.core.trajectory_poses`:
stretches of the path over which the sensor moved a few centimetres, each with the returns taken
from it and its mean sensor position).  Each pseudo-station is a station of the multi-station
ray test (:func:`~app.core.localise.rays.ray_visibility`): its returns, indexed by direction
from its position, say whether it saw the candidate's place empty (rays through the candidate
to returns beyond it), saw a surface there, or could not see it.  The statuses are combined as
for stations (the caller combines them with
:func:`~app.core.localise.station_rays.combine_station_status`).

A ring lidar samples a floor or a box top in lines tens of centimetres apart, wider than a
sample's support disc (:func:`~app.core.localise.gaps.between_samples`).  A candidate no
pseudo-station's rays met near it (edge-on from every one) that lies on a plane the other cloud
sampled all around it is on that surface (a point between two lines measures its distance to
the nearest one); and a ray crossing the candidate's plane between the own cloud's lines
crosses the candidate's surface (:attr:`~app.core.localise.rays.RayTest.gap_radius`).

Cost stays bounded: a candidate is tested only against the pseudo-stations that took the other
cloud's returns nearest to it (they looked at its place) and the few nearest along the path,
within the sensor's range, and, when none of those observed it, the few nearest that had it in
view (:func:`group_views`: a 16-ring lidar sees a seat under it only from metres away); each
pseudo-station indexes only its own returns.

The foot of an upright face (a box's side, a backrest over its seat) within the change
threshold above a support the other epoch sampled near it is unchanged, as in the map test
(:func:`resting_feet`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.localise.distance import Side
from app.core.localise.gaps import NORMAL_AGREEMENT_COSINE, between_samples
from app.core.localise.interface import VisibilityContext, VisibilityOutcome
from app.core.localise.map_parts import surface_parts
from app.core.localise.map_supports import part_bottom, resting_on_support
from app.core.localise.rays import (
    STATUS_EDGE_ON,
    STATUS_SEEN_THROUGH,
    STATUS_SURFACE,
    STATUS_UNOBSERVED,
    Candidates,
    RayTest,
    ray_visibility,
)
from app.core.localise.settings import CHUNK, GATHER_CHUNK
from app.core.localise.station_assignment import rays_from
from app.core.localise.station_rays import combine_station_status, ray_test_for, settle_ray_status
from app.core.localise.surface import LocalGeometry

__all__ = [
    "NEAREST_GROUPS",
    "NEIGHBOUR_RETURNS",
    "GroupViews",
    "TrajectoryTest",
    "candidate_part_bottoms",
    "group_views",
    "resting_feet",
    "resting_on_own_support",
    "trajectory_statuses",
    "undersides_edge_on",
]

LONE_SIGHTING_FACTOR = 1.5
"""A trajectory candidate within this many change thresholds of the other cloud's surface,
seen through by one pseudo-station while others saw it otherwise, is left to the edge-on
resolution (a rack's edge grazed by one stretch of the path)."""

NEIGHBOUR_RETURNS = 16
"""The groups of a candidate's this many nearest returns of the other cloud are tested."""
NEAREST_GROUPS = 4
"""And the groups whose sensor positions are this many nearest to it."""
SENSOR_RANGE = 30.0
"""Metres: a group farther than this from a candidate is not tested against it."""
VIEW_GROUPS, VIEW_SEARCH = 4, 64
"""A candidate none of those observed: the 4 nearest of its 64 nearest groups that had it in
view (:func:`group_views`), within ``VIEW_MARGIN`` radians of their returns' span."""
VIEW_MARGIN = math.radians(1.0)
MIN_GROUP_POINTS = 10
"""A group with fewer returns saw too little to tell anything."""
SURROUNDING_RADIUS_FACTOR = 2.0
"""Samples within this many change thresholds of a place may surround it
(:func:`~app.core.localise.gaps.between_samples`): a candidate between the other cloud's
samples of its plane, and a ray's crossing between the own cloud's samples of the candidate's
plane."""


@dataclasses.dataclass(frozen=True)
class GroupViews:
    """What each of k pseudo-stations' returns span, seen from its sensor position.

    Attributes
    ----------
    lowest, highest : ndarray, shape (k,), float64
        The least and greatest sine of its returns' elevations (a ring lidar's field of view).
    axis : ndarray, shape (k, 3), float64
        Unit mean direction of its returns (any unit vector when they balance out).
    cone_cosine : ndarray, shape (k,), float64
        Cosine of the widest angle of a return from ``axis`` (a camera's frustum).
    reach : ndarray, shape (k,), float64
        Its farthest return's range (metres).
    """

    lowest: NDArray[np.float64]
    highest: NDArray[np.float64]
    axis: NDArray[np.float64]
    cone_cosine: NDArray[np.float64]
    reach: NDArray[np.float64]


def group_views(
    points: NDArray[np.float64],
    origins: NDArray[np.float64],
    rays: tuple[NDArray[np.int64], NDArray[np.int64]],
) -> GroupViews:
    """The span of each pseudo-station's returns (:class:`GroupViews`).

    Parameters
    ----------
    points : ndarray, shape (m, 3)
        The cloud taken along the trajectory.
    origins : ndarray, shape (k, 3)
        Its pseudo-stations' sensor positions.
    rays : (ndarray, ndarray)
        ``(returns, bounds)``: group g's returns are ``points[returns[bounds[g]:bounds[g + 1]]]``.

    Returns
    -------
    GroupViews
        A group without returns sees nothing (an empty elevation span).
    """
    returns, bounds = rays
    count = origins.shape[0]
    group = np.repeat(np.arange(count), np.diff(bounds)[:count])
    lowest, highest = np.full(count, np.inf), np.full(count, -np.inf)
    reach, axis = np.zeros(count), np.zeros((count, 3))
    # in chunks of returns (a cloud without times may have several rays a point)
    for start in range(0, returns.shape[0], CHUNK):
        chunk = slice(start, start + CHUNK)
        direction, distance = rays_from(points[returns[chunk]], origins[group[chunk]])
        np.minimum.at(lowest, group[chunk], direction[:, 2])
        np.maximum.at(highest, group[chunk], direction[:, 2])
        np.maximum.at(reach, group[chunk], distance)
        np.add.at(axis, group[chunk], direction)
    norm = np.linalg.norm(axis, axis=1)
    axis = np.where(norm[:, None] > 1e-9, axis / np.maximum(norm, 1e-12)[:, None], [1.0, 0, 0])
    cone_cosine = np.ones(count)
    for start in range(0, returns.shape[0], CHUNK):
        chunk = slice(start, start + CHUNK)
        direction, _ = rays_from(points[returns[chunk]], origins[group[chunk]])
        along = np.einsum("md,md->m", direction, axis[group[chunk]])
        np.minimum.at(cone_cosine, group[chunk], along)
    return GroupViews(lowest, highest, axis, cone_cosine, reach)


def _nearest_in_view(
    points: NDArray[np.float64], origins: NDArray[np.float64], views: GroupViews
) -> NDArray[np.int64]:
    """The :data:`VIEW_GROUPS` nearest groups within range that had each point in view (within
    their returns' elevation span, cone and reach, :data:`VIEW_MARGIN` wider), shape (c, v),
    -1 for an empty slot."""
    tree = KDTree(origins)
    chunks = range(0, points.shape[0], GATHER_CHUNK)
    found = [_chunk_in_view(points[at : at + GATHER_CHUNK], origins, views, tree) for at in chunks]
    return np.concatenate(found) if found else np.full((0, VIEW_GROUPS), -1, dtype=np.int64)


def _chunk_in_view(
    points: NDArray[np.float64], origins: NDArray[np.float64], views: GroupViews, tree: KDTree
) -> NDArray[np.int64]:
    """:func:`_nearest_in_view` of a chunk of points (``tree`` on ``origins``)."""
    count = points.shape[0]
    k = min(VIEW_SEARCH, origins.shape[0])
    distance, group = tree.query(points, k=k, distance_upper_bound=SENSOR_RANGE)
    distance = np.asarray(distance).reshape(count, k)
    group = np.minimum(np.asarray(group, dtype=np.int64).reshape(count, k), origins.shape[0] - 1)
    direction = (points[:, None, :] - origins[group]) / np.maximum(distance, 1e-12)[..., None]
    margin, elevation = math.sin(VIEW_MARGIN), direction[..., 2]
    from_axis = np.einsum("ckd,ckd->ck", direction, views.axis[group])
    in_view = np.isfinite(distance) & (distance <= views.reach[group])
    in_view &= (elevation >= views.lowest[group] - margin) & (
        from_axis >= views.cone_cosine[group] - margin
    )
    in_view &= elevation <= views.highest[group] + margin
    # the first VIEW_GROUPS in view, nearest first (the query's order)
    rank = np.cumsum(in_view, axis=1)
    chosen = np.full((count, VIEW_GROUPS), -1, dtype=np.int64)
    rows, columns = np.nonzero(in_view & (rank <= VIEW_GROUPS))
    chosen[rows, rank[rows, columns] - 1] = group[rows, columns]
    return chosen


def _group_slots(
    candidates: Candidates, other: Side, origins: NDArray[np.float64]
) -> NDArray[np.int64]:
    """The groups each candidate is tested against, shape (c, s), -1 for an empty slot."""
    assert other.station is not None
    count = candidates.points.shape[0]
    k = min(NEIGHBOUR_RETURNS, other.points.shape[0])
    _, nearest = other.geometry.tree.query(candidates.points, k=k)
    by_returns = other.station[np.asarray(nearest, dtype=np.int64).reshape(count, k)]
    k_groups = min(NEAREST_GROUPS, origins.shape[0])
    distance, nearest_group = KDTree(origins).query(
        candidates.points, k=k_groups, distance_upper_bound=SENSOR_RANGE
    )
    nearest_group = np.asarray(nearest_group, dtype=np.int64).reshape(count, k_groups)
    in_range = np.isfinite(np.asarray(distance).reshape(count, k_groups))
    by_position = np.where(in_range, nearest_group, -1)
    slots = np.sort(np.concatenate([by_returns, by_position], axis=1), axis=1)
    repeated = np.zeros_like(slots, dtype=bool)
    repeated[:, 1:] = slots[:, 1:] == slots[:, :-1]
    slots[repeated] = -1
    return slots


def trajectory_statuses(
    candidates: Candidates, *, own: Side, other: Side, test: RayTest
) -> tuple[NDArray[np.int8], dict[str, Any]]:
    """Ray status of each candidate from each pseudo-station of the other cloud tested.

    Parameters
    ----------
    candidates : Candidates
        c candidates of ``own``.
    own : Side
        The candidates' cloud.
    other : Side
        The other cloud, taken along a trajectory: ``origins`` (k, 3) are its pseudo-stations'
        sensor positions, ``station`` (m,) each return's pseudo-station and
        ``trajectory_rays`` the returns each pseudo-station's rays end on.
    test : RayTest

    Returns
    -------
    statuses : ndarray, shape (s, c), int8
        :func:`~app.core.localise.rays.ray_visibility` status of each candidate from the
        pseudo-station in its slot (STATUS_UNOBSERVED for empty slots: no evidence); combine
        with :func:`~app.core.localise.station_rays.combine_station_status`.
    report : dict
        ``groups`` (the other cloud's pseudo-stations), ``groups_tested`` (those tested against
        some candidate, once a pass), ``candidates_tried_in_view`` (those no pseudo-station of
        the first pass observed, tried from the nearest that had them in view),
        ``tests_per_candidate`` (mean), ``angular_step_deg`` (median of the tested groups').
    """
    assert other.origins is not None and other.station is not None
    assert other.trajectory_rays is not None
    origins = np.asarray(other.origins, dtype=np.float64).reshape(-1, 3)
    count = candidates.points.shape[0]
    report: dict[str, Any] = {"groups": int(origins.shape[0]), "groups_tested": 0}
    if count == 0:
        report.update(tests_per_candidate=0.0, angular_step_deg=math.nan)
        return np.empty((1, 0), dtype=np.int8), report
    slots = _group_slots(candidates, other, origins)
    statuses, angular_steps, tested = _slot_statuses(
        candidates, slots, own=own, other=other, test=test
    )
    # seen by none of those: try the nearest pseudo-stations that had it in view
    unseen = np.flatnonzero((statuses == STATUS_UNOBSERVED).all(axis=0))
    in_view = np.full((count, VIEW_GROUPS), -1, dtype=np.int64)
    if unseen.size:
        views = group_views(other.points, origins, other.trajectory_rays)
        in_view[unseen] = _nearest_in_view(candidates.points[unseen], origins, views)
        in_view[(in_view[:, :, None] == slots[:, None, :]).any(axis=2)] = -1  # tried already
        more, more_steps, more_tested = _slot_statuses(
            candidates, in_view, own=own, other=other, test=test
        )
        statuses = np.concatenate([statuses, more])
        angular_steps, tested = angular_steps + more_steps, tested + more_tested
    report["groups_tested"] = tested
    report["candidates_tried_in_view"] = int(unseen.size)
    report["tests_per_candidate"] = float((slots >= 0).sum() + (in_view >= 0).sum()) / count
    report["angular_step_deg"] = (
        math.degrees(float(np.median(angular_steps))) if angular_steps else math.nan
    )
    return statuses, report


def _slot_statuses(
    candidates: Candidates, slots: NDArray[np.int64], *, own: Side, other: Side, test: RayTest
) -> tuple[NDArray[np.int8], list[float], int]:
    """Ray status of each candidate from the group in each of its ``slots`` (shape (c, s), -1
    empty): statuses shape (s, c) (STATUS_UNOBSERVED for empty slots), each tested group's
    angular step (radians) and how many groups were tested."""
    assert other.origins is not None and other.trajectory_rays is not None
    group_returns, group_bounds = other.trajectory_rays
    origins = np.asarray(other.origins, dtype=np.float64).reshape(-1, 3)
    statuses = np.full(slots.T.shape, STATUS_UNOBSERVED, dtype=np.int8)  # (s, c)
    candidate, slot = np.nonzero(slots >= 0)
    if candidate.size == 0:
        return statuses, [], 0
    group = slots[candidate, slot]
    pair_order = np.argsort(group, kind="stable")
    candidate, slot, group = candidate[pair_order], slot[pair_order], group[pair_order]
    starts = np.flatnonzero(np.r_[True, group[1:] != group[:-1]])
    ends = np.r_[starts[1:], group.size]
    normal, linear = other.geometry.normal, other.geometry.linear
    angular_steps = []
    tested = 0
    for start, end in zip(starts, ends, strict=True):
        number = int(group[start])
        returns = group_returns[group_bounds[number] : group_bounds[number + 1]]
        if returns.size < MIN_GROUP_POINTS:
            continue
        rows = candidate[start:end]
        status, angular_step = ray_visibility(
            candidates.rows(rows),  # type: ignore[arg-type]
            own=own.geometry,
            other_points=other.points[returns],
            other_origin=origins[number],
            test=test,
            other_normals=normal[returns],
            other_linear=linear[returns],
        )
        statuses[slot[start:end], rows] = status
        angular_steps.append(angular_step)
        tested += 1
    return statuses, angular_steps, tested


def lone_sightings(statuses: NDArray[np.int8]) -> NDArray[np.bool_]:
    """Candidates seen through by one pseudo-station only while others saw them otherwise.

    Parameters
    ----------
    statuses : ndarray, shape (s, c), int8

    Returns
    -------
    ndarray, shape (c,), bool
        One slot seen through, and at least one other slot that saw the candidate's surface
        or saw it edge-on (a moving sensor sees a removed object's place from several
        stretches of its path; one ray through a grazed edge is not enough).
    """
    through = (statuses == STATUS_SEEN_THROUGH).sum(axis=0)
    other = ((statuses != STATUS_SEEN_THROUGH) & (statuses != STATUS_UNOBSERVED)).sum(axis=0)
    return (through == 1) & (other >= 1)


def resting_feet(
    candidates: Candidates,
    status: NDArray[np.int8],
    other: Side,
    context: VisibilityContext,
    bottom: NDArray[np.float64],
) -> NDArray[np.bool_]:
    """Candidates seen through or edge-on that rest on the other epoch's support, shape (c,).

    The change distance measures a point against the other cloud's samples, and a sparse map
    samples a floor or a seat in arcs far apart, never under an object standing on it: the
    lowest centimetres of a box's sides or of a backrest over its seat measure farther than
    the change threshold although the support runs under them, within it, in the other epoch's
    world.  The rays see through the foot's place as through the rest of the face; the foot is
    still no change of its own (:func:`~app.core.localise.map_supports.resting_on_support`,
    the map test's rule, with the candidates' surface parts:
    :func:`~app.core.localise.map_parts.surface_parts`).

    Parameters
    ----------
    candidates : Candidates
        c candidates.
    status : ndarray, shape (c,), int8
        Their combined ray statuses.
    other : Side
    context : VisibilityContext
    bottom : ndarray, shape (c,)
        The lowest height of each candidate's surface part (:func:`candidate_part_bottoms`).

    Returns
    -------
    ndarray, shape (c,), bool
    """
    return _feet_on_support(candidates, status, bottom, other.geometry, context)


def undersides_edge_on(
    candidates: Candidates,
    status: NDArray[np.int8],
    own: Side,
    *,
    tolerance: float,
    change_threshold: float,
) -> NDArray[np.bool_]:
    """Level candidates seen edge-on that their own sensor saw from below, shape (c,).

    A desk's or a shelf's underside at about the other sensor's height is seen edge-on from
    every pose of the other path, whatever stands on the desk.  The edge-on resolution
    (:func:`~app.core.localise.station_rays.resolve_edge_on`) promotes an edge-on face joined
    to faces seen through: right for a removed box's top at the sensor's height, which caps
    the faces seen through below it, wrong for the underside of the desk a removed box stood
    on, which the box's faces join from above.  A level surface its own sensor saw from below
    is the underside of something raised, never the top of an object standing on it: seen
    edge-on by the other epoch, it has no evidence and is not promoted.  Its own sensor saw it
    through the space under it, so that space is open: no own point within half the change
    threshold of the place that far (and ``tolerance``) under it (a thin backrest's top edge,
    whose fitted normal may be level, has its own sides just under it).

    Parameters
    ----------
    candidates : Candidates
        c candidates of ``own``.
    status : ndarray, shape (c,), int8
        Their combined ray statuses.
    own : Side
        The candidates' cloud; without sensor positions (``origins`` and ``station``) no
        candidate is an underside.
    tolerance, change_threshold : float
        ``tau`` and ``c`` (metres).

    Returns
    -------
    ndarray, shape (c,), bool
    """
    edge_on = status == STATUS_EDGE_ON
    if own.origins is None or own.station is None or not edge_on.any():
        return np.zeros(status.shape[0], dtype=bool)
    sensor_height = np.asarray(own.origins, dtype=np.float64).reshape(-1, 3)[
        own.station[candidates.index], 2
    ]
    level = np.abs(candidates.normal[:, 2]) >= NORMAL_AGREEMENT_COSINE
    above = edge_on & level & ~candidates.linear & (candidates.points[:, 2] > sensor_height)
    rows = np.flatnonzero(above)
    if rows.size == 0:
        return above
    # the own sensor saw it from below: the space under it is open (a thin body's top edge,
    # its level-fitted normal notwithstanding, has its own sides just under it)
    reach = 0.5 * change_threshold
    under = candidates.points[rows] - np.array([0.0, 0.0, reach + tolerance])
    distance, _ = own.geometry.tree.query(under, k=1, distance_upper_bound=reach)
    above[rows] = ~np.isfinite(np.asarray(distance))
    return above


def resting_on_own_support(
    candidates: Candidates,
    status: NDArray[np.int8],
    sides: tuple[Side, Side],
    context: VisibilityContext,
    bottom: NDArray[np.float64],
) -> NDArray[np.bool_]:
    """Candidates seen through or edge-on on the foot of an upright face whose own support the
    other epoch never saw empty, shape (c,).

    Truth and the change distance call a point unchanged within the change threshold of any
    surface of the other epoch's world.  A box's foot stands within it of the desk or floor
    under it; when the other cloud never sampled that support (a desk top above the other
    sensor's path, a floor between its rings), the rays through the foot's place say the box
    is gone but nothing about the support: the foot may lie within the threshold of it, and
    its own cloud's support is a candidate the other epoch did not see at all (a desk's
    underside, :func:`undersides_edge_on`) or saw a surface at, or not a candidate and
    nearest to a level sample of the other epoch.  Such a foot has no evidence of its own
    (:func:`~app.core.localise.map_supports.resting_on_support` with those own level samples
    only: a removed chair's seat, seen through or promoted with its backrest, carries the
    backrest's foot away; and a seat's sample within the change threshold of a board turned
    across it says nothing of the seat).

    Parameters
    ----------
    candidates : Candidates
        c candidates of ``own``.
    status : ndarray, shape (c,), int8
        Their combined ray statuses.
    sides : (Side, Side)
        The candidates' cloud and the other one.
    context : VisibilityContext
    bottom : ndarray, shape (c,)
        The lowest height of each candidate's surface part (:func:`candidate_part_bottoms`).

    Returns
    -------
    ndarray, shape (c,), bool
    """
    own, other = sides
    # own samples on a level surface of the other epoch (the nearest other point level too) ...
    nearest = own.nearest_index
    unseen = (np.abs(other.geometry.normal[nearest, 2]) >= NORMAL_AGREEMENT_COSINE) & ~(
        other.geometry.linear[nearest]
    )
    unseen[candidates.index] = False
    # ... or candidates it did not see at all, or saw a surface at
    unseen[candidates.index[(status == STATUS_UNOBSERVED) | (status == STATUS_SURFACE)]] = True
    return _feet_on_support(candidates, status, bottom, own.geometry, context, unseen)


def candidate_part_bottoms(
    candidates: Candidates, context: VisibilityContext
) -> NDArray[np.float64]:
    """The lowest height of each candidate's surface part, shape (c,)
    (:func:`~app.core.localise.map_supports.part_bottom` over
    :func:`~app.core.localise.map_parts.surface_parts`): the feet rules' parts."""
    labels = surface_parts(
        candidates.points,
        candidates.normal,
        context.settings["cluster_factor"] * candidates.spacing,
    )
    return part_bottom(candidates.points, labels)


def _feet_on_support(
    candidates: Candidates,
    status: NDArray[np.int8],
    bottom: NDArray[np.float64],
    geometry: LocalGeometry,
    context: VisibilityContext,
    samples: NDArray[np.bool_] | None = None,
) -> NDArray[np.bool_]:
    """Which candidates seen through or edge-on are the foot of an upright face standing on
    ``geometry``'s support (its ``samples`` only, when given), shape (c,): the map test's
    :func:`~app.core.localise.map_supports.resting_on_support` with their parts' ``bottom``."""
    judged = np.flatnonzero((status == STATUS_SEEN_THROUGH) | (status == STATUS_EDGE_ON))
    resting = np.zeros(status.shape[0], dtype=bool)
    if judged.size:
        resting[judged] = resting_on_support(
            candidates.points[judged],
            candidates.normal[judged],
            bottom[judged],
            geometry,
            context.threshold,
            context.change_threshold,
            samples=samples,
        )
    return resting


class TrajectoryTest:
    """The ray test from the pseudo-stations of the other cloud's trajectory
    (``name = "trajectory"``)."""

    name = "trajectory"

    def __call__(
        self, candidates: Candidates, *, own: Side, other: Side, context: VisibilityContext
    ) -> VisibilityOutcome:
        """Statuses from the pseudo-stations tested, lone sightings near the surface left to the
        edge-on resolution."""
        test = dataclasses.replace(
            ray_test_for(own, other, context),
            gap_radius=SURROUNDING_RADIUS_FACTOR * context.change_threshold,
            silhouette_clearance=context.change_threshold,
        )
        statuses, figures = trajectory_statuses(candidates, own=own, other=other, test=test)
        status = combine_station_status(statuses)
        # just past the change threshold: one ray through a grazed edge is not enough
        near = candidates.surface_distance < LONE_SIGHTING_FACTOR * context.change_threshold
        lone = lone_sightings(statuses) & (status == STATUS_SEEN_THROUGH) & near
        status = np.where(lone, STATUS_EDGE_ON, status).astype(np.int8)
        # met by no ray but between the other cloud's samples of its plane: on that surface
        edge_on = np.flatnonzero(status == STATUS_EDGE_ON)
        between = edge_on[
            between_samples(
                candidates.points[edge_on],
                candidates.normal[edge_on],
                other.geometry,
                radius=SURROUNDING_RADIUS_FACTOR * context.change_threshold,
                tolerance=context.threshold,
            )
        ]
        status[between] = STATUS_SURFACE
        # the foot of an upright face on the other epoch's support: no change of its own
        bottom = candidate_part_bottoms(candidates, context)  # both feet rules' parts
        resting = resting_feet(candidates, status, other, context, bottom)
        status[resting] = STATUS_SURFACE
        # a desk's underside the other path saw edge-on: not the removed object's face
        undersides = undersides_edge_on(
            candidates,
            status,
            own,
            tolerance=context.threshold,
            change_threshold=context.change_threshold,
        )
        status[undersides] = STATUS_UNOBSERVED
        # ... and a foot on an own support the other epoch never saw empty: no evidence
        on_unseen_support = resting_on_own_support(
            candidates, status, (own, other), context, bottom
        )
        status[on_unseen_support] = STATUS_UNOBSERVED
        report: dict[str, Any] = {
            "candidates_resting_on_other_support": int(resting.sum()),
            "candidates_resting_on_unseen_support": int(on_unseen_support.sum()),
            "candidates_undersides_edge_on": int(undersides.sum()),
            "candidates_seen_through_once": int(lone.sum()),
            "candidates_between_other_samples": int(between.size),
        }
        report.update({f"other_{name}": value for name, value in figures.items()})
        return settle_ray_status(candidates, status, report, context)
