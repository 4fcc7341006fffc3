"""Plane probes of the map test: does a cloud have surface on a point's plane, and where.

A point of a fused map is judged by whether the other epoch's surface carries on along the
point's own plane (a floor, a wall, a ceiling that continues through a coverage gap), probed in
:data:`SECTORS` directions of the plane at a given reach.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.localise.gaps import NORMAL_AGREEMENT_COSINE, PLANE_SLOPE, tangent_directions
from app.core.localise.rays import Candidates
from app.core.localise.sample_lines import lines_in_planes
from app.core.localise.settings import GATHER_CHUNK
from app.core.localise.surface import LocalGeometry, principal_axes, weighted_plane

__all__ = [
    "COPLANAR_REACHES",
    "COPLANAR_SAMPLE",
    "MUTUAL_FACTOR",
    "SECTORS",
    "SURFACE_REACH",
    "SURFACE_SECTORS",
    "coplanar_sectors",
    "extends",
    "first_level_surface_marked",
    "holds_up",
    "in_sampling_gap",
    "level_surface_below",
    "part_normals",
    "part_sampling_gap",
    "share_on_planes",
    "shared_wall",
    "through_lacking",
    "widest_empty_angle",
]

SURFACE_REACH = 0.8
"""The other epoch's surface must extend this far (metres) from a continuing border point, in
at least :data:`SURFACE_SECTORS` directions of its plane: a floor, a wall, a ceiling, not the
edge of a slid chair's seat."""
SURFACE_SECTORS = 2
SECTORS = 8
SECTOR_HALF_ANGLE_COSINE = math.cos(math.radians(35.0))
PROBE_NEIGHBOURS = 4
COPLANAR_SAMPLE = 256
COPLANAR_REACHES = (0.25, 0.5, 1.0, 2.0)
MUTUAL_FACTOR = 1.0
"""A sample on a candidate's plane is the same surface only when its own plane passes the
candidate within this many change thresholds (:func:`share_on_planes`): surface farther off
is another one, parallel to it (a chair's back 7-13 cm before a wall, robot 2804).  Half a
change threshold also split RGB-D drift room 004's doubled walls (32 -> 80 false points)."""
GAP_REACH = 0.5
"""Metres: the other epoch's points around a candidate that tell whether it lies in a gap
between that epoch's samples of one plane (:func:`in_sampling_gap`)."""
GAP_NEIGHBOURS = 32
GAP_MIN_POINTS = 6
"""Fewer of the other epoch's points on the plane around a candidate than this say nothing."""
PART_PLANE_MIN_POINTS = 8
"""A part of fewer points gives its points no plane of its own (:func:`part_normals`)."""
BELOW_FIRST = 0.05
BELOW_STEP_RATIO = 1.25
BELOW_RADIUS_FRACTION = 0.12
"""The probes under a point: every :data:`BELOW_STEP_RATIO` times farther from
:data:`BELOW_FIRST` down to the reach, each a ball this fraction of its depth wide (as the
see-through probes of :func:`~app.core.localise.origin_free.behind_evidence`)."""


def coplanar_sectors(
    points: NDArray[np.float64],
    normal: NDArray[np.floating],
    cloud: LocalGeometry,
    tolerance: float,
    reach: float,
    lines: bool = False,
    mutual: float | None = None,
) -> NDArray[np.int64]:
    """In how many of :data:`SECTORS` directions of each point's plane ``cloud`` has surface
    on that plane about ``reach`` away (between half and twice it; shapes (p, 3) -> (p,)).

    With ``lines``, a sample of ``cloud`` on a line
    (:func:`~app.core.localise.sample_lines.sample_lines`: its fitted normal says nothing) is
    no surface on the plane, whatever its normal: a line lies in any plane through it.  With
    ``mutual`` (metres), the sample's own plane must pass the point too, within that or the
    plane tolerance, whichever is wider: a face tilted a few degrees off a wall 7-13 cm behind
    it has its plane meet the wall some way off, parallel within the normal agreement, while
    the wall's plane passes the face a change threshold off (robot warehouse 2804's chair
    back)."""
    count = points.shape[0]
    if count == 0:
        return np.zeros(0, dtype=np.int64)
    unit, directions = tangent_directions(normal, SECTORS)
    k = min(PROBE_NEIGHBOURS, cloud.points.shape[0])
    hits = np.zeros((count, SECTORS), dtype=bool)
    for sector in range(SECTORS):
        direction = directions[:, sector, :]
        _, index = cloud.tree.query(points + reach * direction, k=k)
        index = np.asarray(index).reshape(count, k)
        offset = cloud.points[index] - points[:, None, :]
        distance = np.linalg.norm(offset, axis=2)
        across = np.abs(np.einsum("pkd,pd->pk", offset, unit))
        along = np.einsum("pkd,pd->pk", offset, direction)
        agrees = np.abs(np.einsum("pkd,pd->pk", cloud.normal[index], unit))
        placed = (
            (distance <= 2.0 * reach)
            & (along >= SECTOR_HALF_ANGLE_COSINE * distance)
            & (along >= 0.5 * reach)
            & (across <= tolerance + PLANE_SLOPE * distance)
        )
        hit = placed & (agrees >= NORMAL_AGREEMENT_COSINE)
        if mutual is not None:
            passes = np.abs(np.einsum("pkd,pkd->pk", offset, cloud.normal[index]))
            hit &= passes <= np.maximum(tolerance + PLANE_SLOPE * distance, mutual)
        if lines:
            hit &= ~lines_in_planes(cloud, index, unit, hit)[0]
        hits[:, sector] = hit.any(axis=1)
    return hits.sum(axis=1)


def extends(
    points: NDArray[np.float64],
    normal: NDArray[np.floating],
    cloud: LocalGeometry,
    tolerance: float,
    lines: bool = False,
) -> NDArray[np.bool_]:
    """Whether ``cloud`` has surface on each point's plane :data:`SURFACE_REACH` away in at
    least :data:`SURFACE_SECTORS` directions (shapes (p, 3) -> (p,); ``lines`` as
    :func:`coplanar_sectors`')."""
    found = coplanar_sectors(points, normal, cloud, tolerance, SURFACE_REACH, lines)
    return found >= SURFACE_SECTORS


def share_on_planes(
    candidates: Candidates,
    labels: NDArray[np.int64],
    n_clusters: int,
    other: LocalGeometry,
    tolerance: float,
    change_threshold: float,
) -> NDArray[np.float64]:
    """Per cluster, the share of (up to :data:`COPLANAR_SAMPLE`) sampled candidates whose own
    plane the other epoch has within :data:`COPLANAR_REACHES` of them, in some direction, with
    its own plane passing the candidate within :data:`MUTUAL_FACTOR` ``change_threshold``
    (:func:`coplanar_sectors`' ``mutual``).

    A patch of a continuing wall, floor or ceiling lies on the other epoch's plane almost
    everywhere; a removed object's faces do not, even where one of them is in line with a
    surface that stays (a cabinet's front above a cupboard that stays).  A candidate whose own
    plane finds none is probed again on its cluster's plane (:func:`_cluster_planes`): a
    point's own normal, tilted a few degrees by the floor or a corner in its neighbourhood,
    or its sample a few centimetres off the wall by noise, leaves the other epoch's sparse
    samples of the same wall a metre away off its plane (held-out RGB-D room 1904's wall
    behind a desk: 64 % on planes the other epoch has, 94 % on the cluster's plane).  There
    the other epoch's sample must be the same surface: its plane passes the projected point
    within the plane tolerance, not :data:`MUTUAL_FACTOR` change thresholds (a chair back
    tilted 10-15 cm before a wall has a cleaner plane than its points and met the wall).
    """
    rng = np.random.default_rng(0)
    order = rng.permutation(labels.shape[0])
    rank = np.empty_like(order)
    ranked = order[np.argsort(labels[order], kind="stable")]
    starts = np.searchsorted(labels[ranked], np.arange(n_clusters))
    rank[ranked] = np.arange(ranked.shape[0]) - starts[labels[ranked]]
    sample = np.flatnonzero(rank < COPLANAR_SAMPLE)
    points, normal = candidates.points[sample], candidates.normal[sample]
    found = np.zeros(sample.shape[0], dtype=bool)
    mutual = MUTUAL_FACTOR * change_threshold
    for reach in COPLANAR_REACHES:
        todo = np.flatnonzero(~found)
        found[todo] = (
            coplanar_sectors(points[todo], normal[todo], other, tolerance, reach, mutual=mutual)
            >= 1
        )
    on_plane, plane_points, plane_normal = _cluster_planes(points, normal, labels[sample])
    for reach in COPLANAR_REACHES:
        todo = np.flatnonzero(~found & on_plane)
        found[todo] = (
            coplanar_sectors(
                plane_points[todo], plane_normal[todo], other, tolerance, reach, mutual=0.0
            )
            >= 1
        )
    hits = np.bincount(labels[sample], weights=found.astype(np.float64), minlength=n_clusters)
    return hits / np.maximum(np.bincount(labels[sample], minlength=n_clusters), 1)


def _cluster_planes(
    points: NDArray[np.float64], normal: NDArray[np.floating], labels: NDArray[np.int64]
) -> tuple[NDArray[np.bool_], NDArray[np.float64], NDArray[np.float64]]:
    """Each point's cluster's plane: whether the point's normal agrees with it (within
    :data:`~app.core.localise.gaps.NORMAL_AGREEMENT_COSINE`), the point projected onto it and
    its normal (shapes (p, 3) -> (p,), (p, 3), (p, 3)).

    The cluster's normal is the main axis of its points' normals (sign-free); the plane passes
    at the median offset of its points whose normals agree with it.
    """
    unit = np.asarray(normal, dtype=np.float64)
    n_clusters = int(labels.max()) + 1 if labels.shape[0] else 0
    scatter = np.zeros((n_clusters, 3, 3))
    np.add.at(scatter, labels, unit[:, :, None] * unit[:, None, :])
    plane_normal = np.linalg.eigh(scatter)[1][:, :, -1][labels]
    agrees = np.abs(np.einsum("pd,pd->p", unit, plane_normal)) >= NORMAL_AGREEMENT_COSINE
    offset = np.einsum("pd,pd->p", points, plane_normal)
    # the median offset per cluster over its agreeing points: the middle of each sorted run
    chosen = np.flatnonzero(agrees)
    ranked = chosen[np.lexsort((offset[chosen], labels[chosen]))]
    counts = np.bincount(labels[ranked], minlength=n_clusters)
    starts = np.concatenate(([0], np.cumsum(counts)[:-1]))
    level = np.zeros(n_clusters)
    held = counts > 0
    if held.any():
        low = offset[ranked[starts[held] + (counts[held] - 1) // 2]]
        high = offset[ranked[starts[held] + counts[held] // 2]]
        level[held] = 0.5 * (low + high)
    plane_points = points - (offset - level[labels])[:, None] * plane_normal
    return agrees, plane_points, plane_normal


def _probe_below(
    points: NDArray[np.float64],
    cloud: LocalGeometry,
    reach: float,
    min_radius: float,
    marked: NDArray[np.bool_] | None,
    blocking: KDTree | None,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """The probes straight down from each point (shapes (p, 3) -> (p,), (p,)): whether one
    found a level surface of ``cloud`` (or, with ``blocking``, a point of that tree first),
    and whether the probe that found the level surface holds a ``marked`` point."""
    count = points.shape[0]
    found = np.zeros(count, dtype=bool)
    first_marked = np.zeros(count, dtype=bool)
    if count == 0 or cloud.points.shape[0] == 0:
        return found, first_marked
    k = min(PROBE_NEIGHBOURS, cloud.points.shape[0])
    steps = BELOW_FIRST * BELOW_STEP_RATIO ** np.arange(
        math.floor(math.log(reach / BELOW_FIRST, BELOW_STEP_RATIO) + 1e-9) + 1
    )
    for step in steps:
        todo = np.flatnonzero(~found)
        if todo.shape[0] == 0:
            break
        radius = max(min_radius, BELOW_RADIUS_FRACTION * step)
        probes = points[todo] - np.array([0.0, 0.0, step])
        distance, index = cloud.tree.query(probes, k=k, distance_upper_bound=radius)
        distance = np.asarray(distance).reshape(todo.shape[0], k)
        index = np.minimum(np.asarray(index).reshape(todo.shape[0], k), cloud.points.shape[0] - 1)
        level = (distance <= radius) & (
            np.abs(cloud.normal[index][:, :, 2]) >= NORMAL_AGREEMENT_COSINE
        )
        hit = level.any(axis=1)
        if marked is not None:
            first_marked[todo[hit]] = (level & marked[index]).any(axis=1)[hit]
        if blocking is not None:
            block_distance, _ = blocking.query(probes, k=1, distance_upper_bound=radius)
            hit |= np.asarray(block_distance).ravel() <= radius
        found[todo] = hit
    return found, first_marked


def level_surface_below(
    points: NDArray[np.float64], cloud: LocalGeometry, reach: float, min_radius: float
) -> NDArray[np.bool_]:
    """Whether ``cloud`` has a level surface under each point within ``reach`` metres
    (straight down, z up; shapes (p, 3) -> (p,)).

    The probes' balls are :data:`BELOW_RADIUS_FRACTION` of their depth wide, at least
    ``min_radius``; the deepest probe is at ``reach`` or less.  Only downwards: above a top
    lies open air up to a ceiling at any height, which says nothing of what stood under it.
    """
    return _probe_below(points, cloud, reach, min_radius, None, None)[0]


def first_level_surface_marked(
    points: NDArray[np.float64],
    cloud: LocalGeometry,
    reach: float,
    min_radius: float,
    *,
    marked: NDArray[np.bool_],
    blocking: KDTree | None = None,
) -> NDArray[np.bool_]:
    """Whether the first level surface of ``cloud`` under each point (the probes of
    :func:`level_surface_below`) has a ``marked`` point (shape (m,), bool, over ``cloud``'s
    points) in the probe that found it; shapes (p, 3) -> (p,).

    A marked surface farther down, under an unmarked one, does not count; with ``blocking``
    (a tree over other points), a probe that holds one of those before it holds a level
    surface stops the search: False.
    """
    return _probe_below(points, cloud, reach, min_radius, marked, blocking)[1]


def widest_empty_angle(angle: NDArray[np.float64], held: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Per row, the widest angle (radians) holding none of its ``held`` directions ``angle``
    (within +-pi; shapes (b, k) -> (b,)); 2 pi with fewer than two held (or no columns)."""
    if angle.shape[1] == 0:
        return np.full(angle.shape[0], 2.0 * np.pi)
    # the directions not held sort last and repeat the first one
    ordered = np.sort(np.where(held, angle, 4.0 * np.pi), axis=1)
    first = ordered[:, :1] + 2.0 * np.pi
    ordered = np.where(ordered <= np.pi, ordered, first)
    widest = np.diff(np.concatenate([ordered, first], axis=1), axis=1).max(axis=1)
    return np.where(held.sum(axis=1) >= 2, widest, 2.0 * np.pi)


def _largest_empty_angle(
    offset: NDArray[np.float64], on_plane: NDArray[np.bool_], vectors: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Per point, the widest angle (radians) around it in the plane spanned by ``vectors[:, :,
    1:]`` holding none of its ``on_plane`` offsets (shapes (b, k, 3), (b, k), (b, 3, 3) ->
    (b,)); 2 pi with fewer than two."""
    angle = np.arctan2(
        np.einsum("bkd,bd->bk", offset, vectors[:, :, 1]),
        np.einsum("bkd,bd->bk", offset, vectors[:, :, 2]),
    )
    return widest_empty_angle(angle, on_plane)


def in_sampling_gap(
    points: NDArray[np.float64],
    normal: NDArray[np.floating],
    other: LocalGeometry,
    tolerance: float,
    part_normal: NDArray[np.floating] | None = None,
) -> NDArray[np.bool_]:
    """Whether each point lies on a plane the other cloud has around it, between its samples
    (shapes (p, 3), (p, 3) -> (p,)).

    A sparse map samples a floor or a box top far from its path in single scan lines, 0.2-2 m
    apart; the other epoch's lines fall elsewhere, so a line of one epoch lies farther than the
    change distance from every point of the other's, yet on the plane the other's points span,
    with them on every side.  A line has no normal of its own (its neighbours fit any plane
    through it), so the plane is found from the other cloud's points: of its
    :data:`GAP_NEIGHBOURS` nearest within :data:`GAP_REACH`, those within ``tolerance`` (plus
    :data:`~app.core.localise.gaps.PLANE_SLOPE` a metre) of a plane through the point, tried
    with the point's normal, the other cloud's normal there, the level plane and the plane of
    the point's part (``part_normal``, shape (p, 3), when given: :func:`part_normals`), refitted
    once to them.  The point lies in a gap when at least :data:`GAP_MIN_POINTS` of them are on the
    refitted plane through the point and no half-plane around it is empty of them.  A face of
    a removed or added object lies on no plane of the other epoch, or at its edge (a box top
    level with a desk top beside it has the desk on one side only).
    """
    count = points.shape[0]
    found = np.zeros(count, dtype=bool)
    k = min(GAP_NEIGHBOURS, other.points.shape[0])
    if count == 0 or k == 0:
        return found
    level = np.array([0.0, 0.0, 1.0])
    for start in range(0, count, GATHER_CHUNK):
        chunk = slice(start, start + GATHER_CHUNK)
        query = points[chunk]
        distance, index = other.tree.query(query, k=k, distance_upper_bound=GAP_REACH)
        distance = np.asarray(distance).reshape(query.shape[0], k)
        index = np.minimum(np.asarray(index).reshape(query.shape[0], k), other.points.shape[0] - 1)
        offset = other.points[index] - query[:, None, :]
        near = distance <= GAP_REACH
        allowed = tolerance + PLANE_SLOPE * np.where(near, distance, 0.0)
        guesses = [
            normal[chunk].astype(np.float64),
            other.normal[index[:, 0]].astype(np.float64),
            np.broadcast_to(level, query.shape),
        ]
        if part_normal is not None:
            guesses.append(part_normal[chunk].astype(np.float64))
        for guess in guesses:
            on_plane = near & (np.abs(np.einsum("bkd,bd->bk", offset, guess)) <= allowed)
            enough = on_plane.sum(axis=1) >= GAP_MIN_POINTS
            _, _, vectors = weighted_plane(offset, on_plane.astype(np.float64))
            on_plane = near & (np.abs(np.einsum("bkd,bd->bk", offset, vectors[:, :, 0])) <= allowed)
            found[chunk] |= (
                enough
                & (on_plane.sum(axis=1) >= GAP_MIN_POINTS)
                & (_largest_empty_angle(offset, on_plane, vectors) <= np.pi)
            )
    return found


def part_normals(
    points: NDArray[np.float64], labels: NDArray[np.int64], normal: NDArray[np.floating]
) -> NDArray[np.float64]:
    """Per point (shapes (p, 3), (p,), (p, 3) -> (p, 3)), the normal of the plane fitted to
    all the points of its part (``labels``): the smallest eigenvector of their covariance; its
    own ``normal`` in a part of fewer than :data:`PART_PLANE_MIN_POINTS`.

    A strip of a wall one or two sample columns wide, next to the wall's corner, has no normal
    of its own: each point's neighbours are its column, refitted over more neighbours they
    reach round the corner, and its normal is the adjoining wall's (held-out robot corridor
    3401: a 2.7 m strip 5 cm wide, every normal along the wall).  The strip as a whole spans
    the wall's plane."""
    planes = np.asarray(normal, dtype=np.float64).copy()
    for part in np.unique(labels):
        members = np.flatnonzero(labels == part)
        if members.shape[0] < PART_PLANE_MIN_POINTS:
            continue
        planes[members] = principal_axes(points[members])[2][:, 0]
    return planes


def part_sampling_gap(
    candidates: Candidates,
    chosen: NDArray[np.int64],
    labels: NDArray[np.int64],
    other: LocalGeometry,
    tolerance: float,
) -> NDArray[np.bool_]:
    """:func:`in_sampling_gap` of the ``chosen`` candidates (indices, shape (m,) -> (m,)), with
    the plane of each one's part among them (``labels`` shape (c,): :func:`part_normals`)."""
    points, normal = candidates.points[chosen], candidates.normal[chosen]
    planes = part_normals(points, labels[chosen], normal)
    return in_sampling_gap(points, normal, other, tolerance, planes)


def holds_up(
    offset: NDArray[np.float64],
    on_plane: NDArray[np.bool_],
    own_normal: NDArray[np.floating],
    unit: NDArray[np.float64],
    tolerance: float,
    upright_z: float,
) -> NDArray[np.bool_]:
    """Whether the point is on an upright face and the adjoining surface is an upright one
    lying wholly under it: it has points on its plane around the point's foot and none higher
    than ``tolerance`` above it (shapes (b, k, 3), (b, k), (b, 3), (b, 3) -> (b,)).  Upright:
    its normal's vertical component is below ``upright_z``, as a side's is; a crease between
    a level surface and an upright one (the foot of a board on a desk top, its normals
    turning from one to the other) is neither.

    Such a surface ends under the face's foot: the sides of a desk a board stands on, seen
    by a lidar below the desk's top.  Whether it holds the part up is told by the part's
    whole border (:func:`~app.core.localise.map_parts._adjoining_surfaces`): an object's own
    sides meet an unseen side along its height, and near its top corners they lie under a
    border point too (judged per border point, RGB-D room 604 of ``bench.moving_maps``
    gained 1,377 false changed points; robot office 402 is a board on such a desk)."""
    upright = (np.abs(unit[:, 2]) < upright_z) & (
        np.abs(own_normal[:, 2]) < NORMAL_AGREEMENT_COSINE
    )
    above = (on_plane & (offset[:, :, 2] > tolerance)).any(axis=1)
    return upright & on_plane.any(axis=1) & ~above


def shared_wall(
    offset: NDArray[np.float64],
    on_plane: NDArray[np.bool_],
    index: NDArray[np.int64],
    own_normal: NDArray[np.floating],
    unit: NDArray[np.float64],
    lacking: NDArray[np.bool_],
) -> NDArray[np.bool_]:
    """Whether the other epoch's surface adjoining a border point is a wall that both epochs
    saw there: upright, with samples on its plane around the point's foot (``offset`` of the
    other cloud's points ``index``, ``on_plane``; shapes (b, k, 3), (b, k)) on both sides of
    the line where the point's own surface (normal ``own_normal``, shape (b, 3)) meets it
    (normal ``unit``, shape (b, 3)), none of them surface this epoch lacks (``lacking``, shape
    (m,), bool); shape (b,), bool.

    A wall standing clear of an object (a box 9 cm in front of it, a chair's backrest 7 cm
    from it) is seen by both epochs past the object's ends and over its top, whether or not
    the object stood there: it is no face of the object (those end at its edges, on one side
    of the line), and it says nothing either way; such border points do not count as adjoined
    (:func:`~app.core.localise.map_surround.surrounded`).  Where the other epoch saw the object's
    place empty, it saw the wall the object hid from this epoch there: surface this epoch
    lacks.  A sparse map samples a wall in ring lines: it may fill fewer directions around the
    foot than a surface carrying on does, yet lie on both sides of the line."""
    upright = np.abs(unit[:, 2]) < NORMAL_AGREEMENT_COSINE
    both = _on_both_sides(offset, on_plane, own_normal, unit)
    return upright & both & ~(on_plane & lacking[index]).any(axis=1)


def through_lacking(
    offset: NDArray[np.float64],
    on_plane: NDArray[np.bool_],
    marked: NDArray[np.bool_],
    own_normal: NDArray[np.floating],
    unit: NDArray[np.float64],
) -> NDArray[np.bool_]:
    """Whether the other epoch's surface adjoining a border point carries on through the
    point's surface: samples on its plane around the point's foot (``offset``, ``on_plane``;
    shapes (b, k, 3), (b, k)) that are ``marked`` (shape (b, k), bool: surface this epoch
    lacks, not in front of the point's part) on both sides of the line where the point's own
    surface (normal ``own_normal``, shape (b, 3)) meets it (normal ``unit``, shape (b, 3));
    shape (b,), bool.

    An object's other faces end at the edges of the face they adjoin, on one side of the
    face's plane.  A surface of the other epoch that this epoch lacks on both sides of it
    passed through the place where this epoch's object stands: the other epoch's object
    there was another one (robot warehouse 2104, a box turned a quarter in place: the old
    box's side crosses the new box's side, sampled outside it, lacking past the change
    threshold, and inside the new box).  It carries on past the point, as the nearest sample
    being surface this epoch lacks says (:func:`~app.core.localise.map_surround.surrounded`),
    however sparsely it is sampled.  Samples past the line that this epoch has surface for
    (within the change threshold of the point's surface) do not count: on a drifting map the
    other epoch's copy of the same object, a few centimetres off, has its face end just past
    the line (drifting RGB-D room 504: the scan's box side, lacking below the reference's
    top, ends 6 cm over it at a sample the top matches; counted, the box's 1,280 points were
    changed)."""
    return _on_both_sides(offset, on_plane & marked, own_normal, unit)


def _on_both_sides(
    offset: NDArray[np.float64],
    on_plane: NDArray[np.bool_],
    own_normal: NDArray[np.floating],
    unit: NDArray[np.float64],
) -> NDArray[np.bool_]:
    """Whether the ``on_plane`` samples (``offset`` from the point's foot, shapes (b, k, 3),
    (b, k)) lie on both sides of the line where the point's own surface (normal
    ``own_normal``, shape (b, 3)) meets the adjoining plane (normal ``unit``); shape (b,)."""
    edge = np.cross(own_normal.astype(np.float64), unit)
    across = np.cross(unit, edge)
    side = np.einsum("bkd,bd->bk", offset, across)
    return (on_plane & (side > 0.0)).any(axis=1) & (on_plane & (side < 0.0)).any(axis=1)
