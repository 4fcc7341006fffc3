"""Returns given to a station that could not have seen them: moved to one that could.

The rings (:mod:`app.core.localise.station_assignment`) give 1-3 % of a merged survey's points
to the wrong station: a return of station B that happens to lie at the elevation of one of
station A's rings.  Most such returns lie on a surface A saw too, where they do no harm; but a
return that lies *behind* A's own returns in its direction (a rack face that A saw only
through a gap, or not at all) is then one of A's rays ending far beyond A's nearer surface,
and the ray test takes that ray for A's sight through whatever lies in front of it (issue 29,
TLS scene 2104: 381 of the 401 rays passing beyond 52 false points were such returns).

A single-return lidar has one return per ray: a return of A lies in front of no other return
of A in the same direction.  A point whose nearest :data:`NEIGHBOURS` directions among its
station's other returns (within :data:`RADIUS_STEPS` angular steps) all end clearly in front of
it (by :data:`MARGIN_M` and :data:`MARGIN_FRACTION` of its range) is hidden from that station;
a true return just past a silhouette edge keeps neighbours on its own, farther surface.  A
hidden point goes to the station with the highest ring contrast among those it is not hidden
from (else the nearest such station), and the test is repeated once on the stations' new
returns (a hidden return's own misassigned neighbours are gone from them then).

A return misassigned with many of its neighbours (a clump: a stretch of station B's ring that
lies at the elevation of one of A's rings) is not hidden by that test, as its nearest directions
among A's returns are the clump's own, at its own range (TLS 2004: 2,090 of the scan's returns
lay where their assigned station could not see, in clumps of up to 120; 1,649 false changed
points).  A's own surface in front of the clump still has a return within half an angular step
of each clump member's direction (a single-return lidar's rays are about a step apart, so a
nearer return that close is the one in that direction).  The returns of a station linked within
:data:`CLUMP_LINK_STEPS` of its ray gap (angular step x range) form clumps; a clump most of
whose returns have a return of the station in front of them within :data:`CLUMP_COVER_STEPS`
is hidden from the station as a whole, and moves together, to the station most of its
returns are given to by the same choice as a hidden return's.

Cost: each station's returns are seen once a pass (:func:`station_view`: directions, ranges,
their tree and the angular step), shared by both tests of its own returns, by the choice of
the station a hidden return goes to and by the clumps' choice; both tests of its own returns
use one query of the :data:`NEIGHBOURS` nearest directions (:func:`own_tests`), the clump test
querying again only the returns with more neighbours within its cover distance; a station
whose returns did not change keeps its last pass's tests.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.localise.station_assignment import (
    RING_CONTRAST,
    StationGrid,
    grid_contrast,
    rays_from,
    station_contrasts,
)

__all__ = [
    "StationView",
    "hidden_clumps",
    "hidden_from",
    "own_tests",
    "reassign_hidden_returns",
    "station_view",
]

NEIGHBOURS = 4
"""Nearest directions among the station's returns that must all lie in front of a point."""
RADIUS_STEPS = 2.5
"""Those neighbours count within this many of the station's typical angular steps."""
MARGIN_M = 0.05
MARGIN_FRACTION = 0.01
"""A neighbour lies in front when it is nearer the station by this many metres and this share
of the point's range (range noise; a floor seen at a grazing angle rises within a step)."""
SURROUNDED_STEPS = 0.5
"""The neighbours' mean direction lies within this many angular steps of the point's."""
STEP_SAMPLE = 4096
"""Returns whose nearest other return measures the station's typical angular step."""
PASSES = 2
"""Times the hidden returns are looked for and moved."""
CLUMP_LINK_STEPS = 2.0
"""Returns of a station closer than this many angular steps times their range are one clump
(neighbouring rays on one surface are about a step apart in direction)."""
CLUMP_COVER_STEPS = 0.5
"""A return is covered when a return of its station ends in front of it (by the margins)
within this many angular steps of its direction."""
CLUMP_DENSE_STEPS = 0.3
"""A return is too dense for its station when another return of its clump lies within this many
angular steps of its direction (scaled by the cosine of its elevation)."""
MIN_LEVEL = 0.1
"""Smallest cosine of the elevation that scales the step."""
CLUMP_SHARE = 0.5
"""A clump is hidden when at least this share of its returns is covered."""
CLUMP_NEIGHBOURS = 16
"""Nearest directions among the station's returns searched for a covering one (a clump's own
members come first, being nearer in direction than the rays about a step apart)."""
CLUMP_SHARE_TIE = 0.1
"""Stations among whose returns a clump is within this share as odd as the least tie; the
nearest of them takes it."""
CLUMP_LINKS = 8
"""Nearest returns each return is linked to (within the link distance)."""


class StationView(NamedTuple):
    """One station's returns as seen from it, shared by every test of a pass."""

    directions: NDArray[np.float64]
    """Unit directions from the station, shape (m, 3)."""
    ranges: NDArray[np.float64]
    """Ranges, shape (m,)."""
    tree: KDTree
    """Tree of ``directions``."""
    step: float
    """The station's typical angular step (radians)."""


def hidden_from(
    points: NDArray[np.float64],
    origin: NDArray[np.float64],
    returns: NDArray[np.float64],
    *,
    among_returns: bool = False,
    rays: StationView | None = None,
) -> NDArray[np.bool_]:
    """Whether each point lies behind the returns of a station at ``origin`` in its direction.

    Parameters
    ----------
    points : ndarray, shape (c, 3)
    origin : ndarray, shape (3,)
    returns : ndarray, shape (m, 3)
        The station's returns.
    among_returns : bool
        ``points`` are ``returns`` themselves (each point's own direction is then skipped).
    rays : StationView, optional
        :func:`station_view` of ``returns`` (computed when not given).

    Returns
    -------
    ndarray, shape (c,), bool
        Its :data:`NEIGHBOURS` nearest directions among ``returns`` lie within
        :data:`RADIUS_STEPS` of the station's typical angular step and all end in front of it.
    """
    if returns.shape[0] <= NEIGHBOURS + 1 or points.shape[0] == 0:
        return np.zeros(points.shape[0], dtype=bool)
    rays = station_view(returns, origin) if rays is None else rays
    skip = 1 if among_returns else 0
    if among_returns:
        directions, ranges = rays.directions, rays.ranges
    else:
        directions, ranges = rays_from(points, origin)
    distance, index = rays.tree.query(directions, k=NEIGHBOURS + skip)
    return _behind(rays, directions, ranges, distance[:, skip:], index[:, skip:])


def _behind(
    rays: StationView,
    directions: NDArray[np.float64],
    ranges: NDArray[np.float64],
    distance: NDArray[np.float64],
    index: NDArray[np.integer],
) -> NDArray[np.bool_]:
    """:func:`hidden_from`'s test of ``c`` points (``directions`` shape (c, 3), ``ranges``
    shape (c,)) given their :data:`NEIGHBOURS` nearest directions among the station's returns
    (angular ``distance`` and ``index``, shapes (c, NEIGHBOURS)), shape (c,)."""
    margin = np.maximum(MARGIN_M, MARGIN_FRACTION * ranges)
    near = distance <= RADIUS_STEPS * rays.step
    in_front = rays.ranges[index] < (ranges - margin)[:, None]
    # on all sides of the point: the edge of the station's field of view has its returns on
    # one side only (nearer ones, on a surface seen obliquely there)
    off_centre = np.linalg.norm(rays.directions[index].mean(axis=1) - directions, axis=1)
    return np.all(near & in_front, axis=1) & (off_centre <= SURROUNDED_STEPS * rays.step)


def station_view(returns: NDArray[np.float64], origin: NDArray[np.float64]) -> StationView:
    """A station's returns (shape (m, 3)) as seen from ``origin`` (shape (3,)): their
    directions, ranges, a tree of the directions and the typical angular step (radians)."""
    directions, ranges = rays_from(returns, origin)
    tree = KDTree(directions)
    sample = directions[:: max(1, directions.shape[0] // STEP_SAMPLE)]
    step = float(np.median(tree.query(sample, k=2)[0][:, 1]))
    return StationView(directions, ranges, tree, step)


def hidden_clumps(
    returns: NDArray[np.float64],
    origin: NDArray[np.float64],
    rays: StationView | None = None,
) -> NDArray[np.int64]:
    """The clumps of a station's returns that the station could not have taken.

    Parameters
    ----------
    returns : ndarray, shape (m, 3)
        The returns assigned to the station at ``origin`` (shape (3,)).
    rays : StationView, optional
        :func:`station_view` of ``returns`` (computed when not given).

    Returns
    -------
    ndarray, shape (m,), int64
        Clump label of each return in such a clump (:data:`CLUMP_SHARE` of its returns are
        covered or too dense, :func:`_odd_returns`), -1 for the others.
    """
    return own_tests(returns, origin, rays)[1]


def own_tests(
    returns: NDArray[np.float64],
    origin: NDArray[np.float64],
    rays: StationView | None = None,
) -> tuple[NDArray[np.bool_], NDArray[np.int64]]:
    """:func:`hidden_from` (``among_returns``) and :func:`hidden_clumps` of a station's
    returns (shape (m, 3)), from one query of their directions, shapes (m,) and (m,)."""
    count = returns.shape[0]
    clump = np.full(count, -1, dtype=np.int64)
    if count <= CLUMP_NEIGHBOURS:
        return hidden_from(returns, origin, returns, among_returns=True, rays=rays), clump
    rays = station_view(returns, origin) if rays is None else rays
    squared, index = rays.tree.query(rays.directions, k=NEIGHBOURS + 1, sqr_dists=True)
    distance = np.sqrt(squared)
    hidden = _behind(rays, rays.directions, rays.ranges, distance[:, 1:], index[:, 1:])
    near, near_index = _cover_neighbours(rays, squared, distance, index)
    labels = _clumps(returns, CLUMP_LINK_STEPS * rays.step * rays.ranges)
    odd = _odd_returns(
        rays.directions,
        rays.ranges,
        rays.step,
        (near, rays.ranges[near_index]),
        (near, labels[near_index] == labels[:, None]),
    )
    total = int(labels.max()) + 1
    share = np.bincount(labels, odd, total) / np.bincount(labels, minlength=total)
    in_hidden = share[labels] >= CLUMP_SHARE
    clump[in_hidden] = labels[in_hidden]
    return hidden, clump


def _cover_neighbours(
    rays: StationView,
    squared: NDArray[np.float64],
    distance: NDArray[np.float64],
    index: NDArray[np.integer],
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """The :data:`CLUMP_NEIGHBOURS` nearest other directions of each of the station's ``m``
    returns within :data:`CLUMP_COVER_STEPS` (angular distance, inf beyond, and index), shapes
    (m, CLUMP_NEIGHBOURS).

    From the :data:`NEIGHBOURS` + 1 nearest (``squared`` and ``distance``, ``index``, shapes
    (m, NEIGHBOURS + 1), the first the return itself) where the last of them lies beyond the
    bound (then so does every farther one); the others are queried with the bound, as the
    tree marks them (a squared distance at or over the squared bound is beyond it).
    """
    count = rays.ranges.shape[0]
    bound = CLUMP_COVER_STEPS * rays.step
    near = np.full((count, CLUMP_NEIGHBOURS), np.inf)
    near_index = np.full((count, CLUMP_NEIGHBOURS), count - 1, dtype=np.int64)
    inside = squared[:, 1:] < bound * bound
    near[:, :NEIGHBOURS] = np.where(inside, distance[:, 1:], np.inf)
    near_index[:, :NEIGHBOURS] = index[:, 1:]
    more = np.flatnonzero(inside[:, -1])
    if more.size:
        far, far_index = rays.tree.query(
            rays.directions[more], k=CLUMP_NEIGHBOURS + 1, distance_upper_bound=bound
        )
        near[more] = far[:, 1:]
        near_index[more] = np.minimum(far_index[:, 1:], count - 1)
    return near, near_index


def _odd_returns(
    directions: NDArray[np.float64],
    ranges: NDArray[np.float64],
    step: float,
    nearest: tuple[NDArray[np.float64], NDArray[np.float64]],
    fellows: tuple[NDArray[np.float64], NDArray[np.bool_]],
) -> NDArray[np.bool_]:
    """Whether each of ``c`` returns of a clump is one its station could not have taken.

    Parameters
    ----------
    directions : ndarray, shape (c, 3)
        From the station.
    ranges : ndarray, shape (c,)
    step : float
        The station's typical angular step (radians).
    nearest : (ndarray, ndarray), shapes (c, j)
        Angular distance to, and range of, the station's other returns nearest in direction.
    fellows : (ndarray, ndarray), shapes (c, l)
        Angular distance to the nearest returns in direction among the clump's (itself
        excluded), and whether each is of the same clump.

    Returns
    -------
    ndarray, shape (c,), bool
        Covered (a return of the station ends in front of it, by the margins, within
        :data:`CLUMP_COVER_STEPS` of its direction) or too dense (another return of its clump
        within :data:`CLUMP_DENSE_STEPS` of its direction: another station's samples of a
        surface nearer to that station; the step shrinks with the cosine of the elevation, as
        rays converge towards the zenith and the nadir).
    """
    margin = np.maximum(MARGIN_M, MARGIN_FRACTION * ranges)
    in_front = nearest[1] < (ranges - margin)[:, None]
    covered = np.any(in_front & (nearest[0] <= CLUMP_COVER_STEPS * step), axis=1)
    level = np.sqrt(np.maximum(1.0 - directions[:, 2] ** 2, 0.0))
    nearest_fellow = np.where(fellows[1], fellows[0], np.inf).min(axis=1)
    dense = nearest_fellow < CLUMP_DENSE_STEPS * step * np.maximum(level, MIN_LEVEL)
    return covered | dense


def _clump_shares(
    points: NDArray[np.float64],
    origins: NDArray[np.float64],
    station: NDArray[np.int64],
    members: NDArray[np.int64],
    labels: NDArray[np.int64],
    rays: list[StationView | None],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """How odd each moved clump would be among each other station's returns, and how far.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    origins : ndarray, shape (k, 3)
    station : ndarray, shape (n,), int64
        Each point's station now.
    members : ndarray, shape (c,), int64
        Indices of the moved clumps' returns.
    labels : ndarray, shape (c,), int64
        Clump number (0 .. L-1) of each member.
    rays : list of StationView or None, length k
        :func:`station_view` of each station's returns now (None: none taken yet).

    Returns
    -------
    share : ndarray, shape (L, k)
        Share of each clump's returns that :func:`_odd_returns` finds odd as the station's
        (inf for its own station and for stations with too few returns).
    distance : ndarray, shape (L, k)
        Mean range of each clump from each station.
    """
    count = int(labels.max()) + 1
    size = np.bincount(labels, minlength=count)
    share = np.full((count, origins.shape[0]), np.inf)
    distance = np.full((count, origins.shape[0]), np.inf)
    for number, origin in enumerate(origins):
        rows = np.flatnonzero(station[members] != number)
        if rows.size <= CLUMP_LINKS or np.count_nonzero(station == number) <= CLUMP_NEIGHBOURS:
            continue
        own = points[station == number]
        seen = rays[number] if rays[number] is not None else station_view(own, origin)
        own_ranges, tree, step = seen.ranges, seen.tree, seen.step
        directions, ranges = rays_from(points[members[rows]], origin)
        near, index = tree.query(directions, k=CLUMP_NEIGHBOURS)
        fellow, fellow_index = KDTree(directions).query(directions, k=CLUMP_LINKS + 1)
        same = labels[rows][fellow_index[:, 1:]] == labels[rows][:, None]
        odd = _odd_returns(
            directions, ranges, step, (near, own_ranges[index]), (fellow[:, 1:], same)
        )
        whole = np.bincount(labels[rows], minlength=count) == size
        share[whole, number] = (np.bincount(labels[rows], odd, count) / np.maximum(size, 1))[whole]
        distance[whole, number] = (np.bincount(labels[rows], ranges, count) / np.maximum(size, 1))[
            whole
        ]
    return share, distance


def _clump_station(
    points: NDArray[np.float64],
    origins: NDArray[np.float64],
    station: NDArray[np.int64],
    members: NDArray[np.int64],
    clump: NDArray[np.int64],
    chosen: NDArray[np.int64],
    rays: list[StationView | None],
) -> NDArray[np.int64]:
    """The station each moved clump's returns go to, together, shape (c,).

    The clump goes to the station among whose returns it is least odd (:func:`_clump_shares`;
    of those within :data:`CLUMP_SHARE_TIE` of the least, the nearest), when that share is
    under :data:`CLUMP_SHARE`: the station that could have taken it; else to the station
    ``chosen`` (shape (c,): each return's choice as a hidden one's) for most of its returns.
    ``members`` (shape (c,)) index ``points``; ``clump`` (shape (c,)) labels their clumps;
    ``rays``: :func:`station_view` of each station's returns now.
    """
    _, labels = np.unique(clump, return_inverse=True)
    labels = labels.ravel()
    share, distance = _clump_shares(points, origins, station, members, labels, rays)
    least = share.min(axis=1)
    near_least = share <= (least + CLUMP_SHARE_TIE)[:, None]
    best = np.argmin(np.where(near_least, distance, np.inf), axis=1)
    votes = np.zeros((share.shape[0], origins.shape[0]), dtype=np.int64)
    np.add.at(votes, (labels, chosen), 1)
    together = np.where(least < CLUMP_SHARE, best, np.argmax(votes, axis=1))
    return together[labels]


def _clumps(points: NDArray[np.float64], radius: NDArray[np.float64]) -> NDArray[np.int64]:
    """Connected components of ``points`` (shape (m, 3)) linked to their :data:`CLUMP_LINKS`
    nearest neighbours within their own ``radius`` (shape (m,)), shape (m,)."""
    from scipy.sparse import coo_matrix  # on first use: API processes need no scipy
    from scipy.sparse.csgraph import connected_components

    count = points.shape[0]
    k = min(CLUMP_LINKS + 1, count)
    tree = KDTree(points)
    rows, columns = [], []
    # queried by bands of radius, each bounded by its largest: the same links, found sooner
    band = np.floor(np.log(np.maximum(radius, 1e-9) / max(radius.min(), 1e-9)) / np.log(1.5))
    for value in np.unique(band):
        part = np.flatnonzero(band == value)
        distance, neighbour = tree.query(
            points[part], k=k, distance_upper_bound=float(radius[part].max())
        )
        linked = distance[:, 1:] <= radius[part, None]
        rows.append(np.repeat(part, k - 1)[linked.ravel()])
        columns.append(neighbour[:, 1:][linked])
    graph = coo_matrix(
        (
            np.ones(sum(r.shape[0] for r in rows), dtype=np.int8),
            (np.concatenate(rows), np.concatenate(columns)),
        ),
        (count, count),
    )
    return connected_components(graph, directed=True, connection="weak")[1].astype(np.int64)


def reassign_hidden_returns(
    points: NDArray[np.float64], origins: NDArray[np.float64], station: NDArray[np.integer]
) -> NDArray[np.int64]:
    """``station`` with each return hidden from its station moved to one that could see it.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    origins : ndarray, shape (k, 3)
    station : ndarray, shape (n,), int
        Index into ``origins`` of each point's station (from its rings).

    Returns
    -------
    ndarray, shape (n,), int64
    """
    points = np.asarray(points, dtype=np.float64)
    origins = np.asarray(origins, dtype=np.float64)
    station = np.asarray(station, dtype=np.int64).copy()
    if origins.shape[0] < 2:
        return station
    contrasts = None
    tested: list[_Tested | None] = [None] * origins.shape[0]
    for _ in range(PASSES):
        hidden = np.zeros(points.shape[0], dtype=bool)
        clump = np.full(points.shape[0], -1, dtype=np.int64)
        for number, origin in enumerate(origins):
            tested[number] = _station_tests(points, origin, station == number, tested[number])
            own, own_hidden, labels = tested[number][:3]
            hidden[own] = own_hidden
            members = labels >= 0
            # clump labels unique over the stations
            clump[own[members]] = labels[members] + clump.max() + 1
            hidden[own[members]] = True
        moved = np.flatnonzero(hidden)
        if moved.size == 0:
            break
        if contrasts is None:
            contrasts = station_contrasts(points, origins)
        rays = [found.rays for found in tested]
        chosen = _seeing_station(points, origins, station, moved, contrasts, rays)
        in_clump = clump[moved] >= 0
        if in_clump.any():
            chosen[in_clump] = _clump_station(
                points,
                origins,
                station,
                moved[in_clump],
                clump[moved[in_clump]],
                chosen[in_clump],
                rays,
            )
        station[moved] = chosen
    return station


class _Tested(NamedTuple):
    """One station's returns and what the tests of a pass found for them."""

    own: NDArray[np.int64]
    """Indices of its returns, shape (m,)."""
    hidden: NDArray[np.bool_]
    """:func:`hidden_from` each of them, shape (m,)."""
    clump: NDArray[np.int64]
    """:func:`hidden_clumps` label of each, shape (m,)."""
    rays: StationView | None
    """:func:`station_view` of them (None: too few for any test)."""


def _station_tests(
    points: NDArray[np.float64],
    origin: NDArray[np.float64],
    mine: NDArray[np.bool_],
    before: _Tested | None,
) -> _Tested:
    """The tests of one station's returns (``mine``, shape (n,), of ``points``, shape (n, 3));
    the last pass's (``before``) when its returns are the same (the tests depend on them and
    ``origin`` alone: nothing moved to or from it)."""
    own = np.flatnonzero(mine)
    if before is not None and np.array_equal(before.own, own):
        return before
    returns = points[own]
    rays = station_view(returns, origin) if own.size > NEIGHBOURS + 1 else None
    return _Tested(own, *own_tests(returns, origin, rays), rays)


def _seeing_station(
    points: NDArray[np.float64],
    origins: NDArray[np.float64],
    station: NDArray[np.int64],
    moved: NDArray[np.int64],
    contrasts: list[StationGrid],
    rays: list[StationView | None],
) -> NDArray[np.int64]:
    """For the hidden points ``moved`` (indices, shape (h,)): the station with the highest grid
    contrast among those they are not hidden from (on no such station's rings: the nearest of
    them; hidden from all: their own), shape (h,).  ``rays``: :func:`station_view` of each
    station's returns now."""
    score = np.full((moved.size, origins.shape[0]), -np.inf)
    distance = np.full((moved.size, origins.shape[0]), np.inf)
    for number, origin in enumerate(origins):
        candidates = station[moved] != number
        if not candidates.any():
            continue
        rows = np.flatnonzero(candidates)
        own = points[station == number]
        seen = ~hidden_from(points[moved[rows]], origin, own, rays=rays[number])
        rows = rows[seen]
        score[rows, number] = grid_contrast(points[moved[rows]], origin, contrasts[number])
        distance[rows, number] = np.linalg.norm(points[moved[rows]] - origin, axis=1)
    best = np.argmax(score, axis=1)
    on_rings = score[np.arange(moved.size), best] >= RING_CONTRAST
    nearest = np.argmin(distance, axis=1)
    chosen = np.where(on_rings, best, nearest)
    return np.where(np.isfinite(score).any(axis=1), chosen, station[moved])
