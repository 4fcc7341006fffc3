"""Bodies in the other epoch's blind area: what stands where the other path never looked.

The map test judges a cluster of candidates by the evidence on and around its surface parts
(:func:`~app.core.localise.map_evidence.map_test`).  A piece of furniture that no pose of the
other epoch could see gives no evidence either way: its top has the floor both epochs saw
beneath it (reachable under a raised body), its sides have nothing behind them and meet
nothing, so they fall to the default for a cluster near the other epoch's coverage, a change.
A removed chair or table gives the same figures part by part.

What differs is the body's surroundings.  Where the other epoch saw a removed object's place,
it also saw what stands around it: the floor around its feet, the wall behind it, the desk it
stood on.  Those surroundings are in both epochs, so this epoch's points there are matched
(no candidates).  Where the other path never looked, the surfaces around the body, which
stand in both epochs, were not seen either: this epoch's points around it are candidates the
map test already judged coverage differences (the wall behind an unchanged desk that a
handheld camera never filmed, while it filmed the floor under the desk from the side).

:func:`blind_clusters` takes each body, a cluster of the change parts' candidates and the
small coverage parts among them (:func:`_bodies`: a larger coverage difference is the
surroundings; joined in, it made one cluster of a cabinet in an unfilmed corner and a wall
band 1.5 m away, its shell the matched points round both, held-out RGB-D room 1904), and
looks at this epoch's points around it, within
:data:`SHELL_FACTOR` change thresholds of its candidates and outside it, and more than one
change threshold over its lowest candidate (the floor or desk it stands on is no
surrounding: the other path may have missed the floor round an added box's foot):
when at least :data:`BLIND_SHARE` of them are other clusters' coverage differences, the whole
cluster lies in the other epoch's blind area and is one too.  (Judging each change part
alone on its own shell as well, s21, cleared a wall band's patches on dense rooms but took a
removed chair in a dense RGB-D room from 95 to 17 % and real bicycles from 82 to 75 %: not
kept.)  No sensor position, no ring pattern: the shell is measured in metres of the change
threshold, the verdict in shares of this cloud's own points.

A shell point the other epoch holds only by isolated samples (:func:`held_by_isolated`: no
surface of the other epoch within the change threshold, only samples alone in the air, off
their neighbours' plane) is no evidence that the other path saw the place: a fused map's
flying pixels stand where its camera looked past an edge, not on the surface they hold.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from pykdtree.kdtree import KDTree

from app.core.localise.distance import Side
from app.core.localise.map_fragments import host_coverage
from app.core.localise.map_parts import PartFigures
from app.core.localise.map_planes import level_surface_below
from app.core.localise.map_shared import MIN_ADJOINING
from app.core.localise.map_sides import SPARSE_PROBE_FACTOR
from app.core.localise.map_surround import ADJOINING_FACTOR
from app.core.localise.origin_free import BEHIND_MIN_RADIUS
from app.core.localise.rays import Candidates
from app.core.localise.regions import cluster_labels
from app.core.localise.surface import LocalGeometry, neighbourhood_planes

__all__ = [
    "BLIND_SHARE",
    "OFF_PLANE",
    "SHELL_FACTOR",
    "blind_clusters",
    "held_by_isolated",
    "seen_round",
    "settled_coverage",
]

SHELL_FACTOR = 3.0
"""The shell around a cluster reaches this many change thresholds from its candidates (0.3 m
at 10 cm): the wall behind a desk against it, the floor around a chair's feet."""
BLIND_SHARE = 0.5
"""A cluster is in the other epoch's blind area when this share of its shell is coverage
differences (RGB-D room 9's unchanged desk, size 2: 0.81; every true change of RGB-D seeds
0-2 and of the real pairs, the removed table and fence among them: 0.00-0.05)."""
SEEN_AROUND_SHARE = 0.5
"""A cluster with a change part whose adjoining border points (at least
:data:`~app.core.localise.map_shared.MIN_ADJOINING`) have the other epoch's surface carrying on
past them in this share is no blind area: the other epoch saw round it (a removed board high
on a wall, the ceiling over it seen by the other path, the wall round it not: RGB-D room 700,
once a dense map's wall band there was a coverage difference)."""
MIN_SHELL_POINTS = 20
"""Fewer shell points say nothing about the surroundings (a cluster in mid-air)."""
ISOLATION = 4.0
"""Median spacings: an isolated sample has at most :data:`ISOLATED_NEIGHBOURS` samples of its
map within this (as :data:`~app.core.localise.flying_samples.ISOLATION`)."""
ISOLATED_NEIGHBOURS = 2
"""Samples an isolated sample may have within :data:`ISOLATION` median spacings."""
OFF_PLANE = 2.0
"""An isolated sample of the other epoch (:data:`ISOLATION`) this many median spacings
or more off the plane of its :data:`PLANE_NEIGHBOURS` nearest samples has no surface of its
own: a flying pixel in front of a far wall whose samples are its neighbours (drifting RGB-D
room 503's reference holders of the turned chair: 18-55 cm off their surface)."""
PLANE_NEIGHBOURS = 10
"""Samples whose plane an isolated sample is measured against (itself not counted)."""
DENSE_SPACING = 0.025
"""Metres: only a map with a median spacing under this has flying pixels (a fused RGB-D map; as
:data:`~app.core.localise.flying_samples.DENSE_SPACING`): a robot map's or a lidar scan's lone
samples are ring arcs and far surfaces, evidence of sight."""
HOLDERS = 16
"""The other epoch's samples looked at within the change threshold of a shell point: a point
with this many is held by a surface."""


def blind_clusters(
    points: NDArray[np.float64],
    candidate_index: NDArray[np.int64],
    candidate_radius: NDArray[np.float64],
    labels: NDArray[np.int64],
    coverage: NDArray[np.bool_],
    change_threshold: float,
    seen_around: NDArray[np.bool_] | None = None,
    faces: NDArray[np.bool_] | None = None,
    other: LocalGeometry | None = None,
) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
    """Per surface part, whether its cluster lies in the other epoch's blind area, and the
    share of the cluster's shell that is coverage differences (module docstring).

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        This epoch's cloud.
    candidate_index : ndarray, shape (c,), int64
        The change candidates' indices into ``points``.
    candidate_radius : ndarray, shape (c,)
        Candidates within a candidate's radius are one cluster (as the map test's
        nearness is judged).
    labels : ndarray, shape (c,), int64
        Surface part of each candidate.
    coverage : ndarray, shape (parts,), bool
        The map test's verdict per part: a coverage difference.
    change_threshold : float
        ``c`` (metres).
    seen_around : ndarray, shape (parts,), bool, optional
        Parts round which the other epoch saw (:data:`SEEN_AROUND_SHARE`): a cluster with
        such a change part is never blind.
    faces : ndarray, shape (parts,), bool, optional
        Parts that are coverage differences as unseen faces only: the other epoch saw the
        faces of their object that meet them, so it looked there, and they are no blind
        surroundings.  A box or chair turned in place has its new face where the old object
        stood as an unseen face, and the rest of the turned object beside it was taken into
        the blind area on that face alone (held-out robot 2604's turned box, 2204's turned
        chair).
    other : LocalGeometry, optional
        The other epoch's samples (aligned): a shell point they hold only by isolated samples
        counts as unseen (:func:`held_by_isolated`).

    Returns
    -------
    blind : ndarray, shape (parts,), bool
        The part's cluster has a change part and lies in the blind area.
    share : ndarray, shape (parts,), float64
        Its cluster's shell share of coverage differences (0 where not looked at).
    """
    n_parts = coverage.shape[0]
    blind, share = np.zeros(n_parts, dtype=bool), np.zeros(n_parts)
    if candidate_index.shape[0] == 0 or coverage[labels].all():
        return blind, share
    candidates = points[candidate_index]
    members = _bodies(candidates, candidate_radius, labels, coverage)
    clusters = np.full(candidates.shape[0], -1, dtype=np.int64)
    clusters[members] = cluster_labels(candidates[members], candidate_radius[members])
    n_clusters = int(clusters.max()) + 1
    changing = np.zeros(n_clusters, dtype=bool)
    changing[clusters[~coverage[labels]]] = True
    seen = np.zeros(n_clusters, dtype=bool)
    if seen_around is not None:
        seen[clusters[~coverage[labels] & seen_around[labels]]] = True
    members &= changing[clusters]
    reach = SHELL_FACTOR * change_threshold
    low = candidates[members].min(axis=0) - reach
    high = candidates[members].max(axis=0) + reach
    looked = np.flatnonzero(np.all((points >= low) & (points <= high), axis=1))
    in_member = np.zeros(points.shape[0], dtype=bool)
    in_member[candidate_index[members]] = True
    looked = looked[~in_member[looked]]
    if looked.shape[0] == 0:
        return blind, share
    distance, nearest = KDTree(candidates[members]).query(
        points[looked], k=1, distance_upper_bound=reach
    )
    shell = np.asarray(distance).ravel() <= reach
    owner = clusters[np.flatnonzero(members)[np.asarray(nearest).ravel()[shell]]]
    # the support it stands on is no surrounding: only points over its foot count
    bottom = np.full(n_clusters, np.inf)
    np.minimum.at(bottom, clusters[members], candidates[members, 2])
    raised = points[looked[shell], 2] > bottom[owner] + change_threshold
    shell[np.flatnonzero(shell)[~raised]] = False
    owner = owner[raised]
    is_candidate = np.zeros(points.shape[0], dtype=bool)
    is_candidate[candidate_index] = True
    in_candidates = is_candidate.copy()
    # shell points that are candidates are no change parts' (those are left out): coverage,
    # unless an unseen face's (the other epoch saw its object's faces meeting it: it looked there)
    if faces is not None:
        is_candidate[candidate_index[faces[labels]]] = False
    unseen = is_candidate[looked[shell]]
    if other is not None:
        held = np.flatnonzero(~in_candidates[looked[shell]])
        unseen[held] |= held_by_isolated(points[looked[shell][held]], other, change_threshold)
    unseen = unseen.astype(np.float64)
    totals = np.bincount(owner, minlength=n_clusters).astype(np.float64)
    unseen_share = np.bincount(owner, weights=unseen, minlength=n_clusters) / np.maximum(
        totals, 1.0
    )
    in_blind = changing & ~seen & (totals >= MIN_SHELL_POINTS) & (unseen_share >= BLIND_SHARE)
    blind[labels[members]] = in_blind[clusters[members]]
    share[labels[members]] = unseen_share[clusters[members]]
    return blind, share


def held_by_isolated(
    points: NDArray[np.float64], other: LocalGeometry, change_threshold: float
) -> NDArray[np.bool_]:
    """Which ``points`` (shape (m, 3)) the ``other`` epoch holds only by isolated samples,
    shape (m,), bool: one of its samples within ``change_threshold``, and each of them there
    isolated and off its neighbours' plane (:data:`ISOLATION`, :data:`OFF_PLANE`: a flying
    pixel, no surface).  A point with :data:`HOLDERS` samples there is held by a surface.  All
    False unless ``other`` is dense (:data:`DENSE_SPACING`)."""
    held = np.zeros(points.shape[0], dtype=bool)
    count = other.points.shape[0]
    spacing = float(np.median(other.spacing)) if count else 0.0
    if points.shape[0] == 0 or count <= PLANE_NEIGHBOURS or spacing >= DENSE_SPACING:
        return held
    distance, holder = other.tree.query(points, k=HOLDERS, distance_upper_bound=change_threshold)
    near = np.isfinite(distance)
    few = np.flatnonzero(near[:, 0] & ~near[:, -1])
    holder, near = np.minimum(holder[few], count - 1), near[few]
    holders = np.unique(holder[near])
    if holders.shape[0] == 0:
        return held
    around, neighbour = other.tree.query(other.points[holders], k=PLANE_NEIGHBOURS + 1)
    normal, plane_constant, *_ = neighbourhood_planes(other.points, neighbour[:, 1:])
    off = np.abs(np.einsum("ni,ni->n", other.points[holders], normal) - plane_constant)
    lone = np.zeros(count, dtype=bool)
    isolated = around[:, ISOLATED_NEIGHBOURS + 1] > ISOLATION * spacing
    lone[holders[isolated & (off >= OFF_PLANE * spacing)]] = True
    held[few] = ~(near & ~lone[holder]).any(axis=1)
    return held


def _bodies(
    candidates: NDArray[np.float64],
    radius: NDArray[np.float64],
    labels: NDArray[np.int64],
    coverage: NDArray[np.bool_],
) -> NDArray[np.bool_]:
    """The candidates (shape (c,), bool) that make up the bodies judged for blind areas: the
    change parts' candidates, and those of each coverage part with fewer candidates than the
    change parts of its cluster of candidates (shapes as :func:`blind_clusters`').

    A small coverage difference among a body's changes is a piece of it (a board's top edge
    that only one path looked down on); a larger one is its surroundings (the back wall behind
    a cabinet in a corner the other path never filmed, which joined the cabinet into one
    cluster with a wall band 1.5 m away: held-out RGB-D room 1904).
    """
    change = ~coverage[labels]
    clusters = cluster_labels(candidates, radius)
    changes_per_cluster = np.bincount(clusters[change], minlength=int(clusters.max()) + 1)
    part_size = np.bincount(labels, minlength=coverage.shape[0])
    return change | (part_size[labels] < changes_per_cluster[clusters])


def seen_round(
    figures: PartFigures,
    candidates: Candidates,
    labels: NDArray[np.int64],
    other: Side,
    change_threshold: float,
) -> NDArray[np.bool_]:
    """Per part, whether the other epoch saw round it (shape (parts,), bool): at least
    :data:`~app.core.localise.map_shared.MIN_ADJOINING` adjoining border points, the other
    epoch's surface carrying on past :data:`SEEN_AROUND_SHARE` of them, and the part hanging
    free: under fewer than half of its foot's candidates (within ``change_threshold`` of its
    lowest) the other epoch has a level surface within
    :data:`~app.core.localise.map_surround.ADJOINING_FACTOR` change thresholds (a board on a
    wall, not a desk's leg on the floor the other path filmed round it)."""
    check = (figures.adjoining >= MIN_ADJOINING) & (figures.surround_share >= SEEN_AROUND_SHARE)
    chosen = np.flatnonzero(check[labels])
    if chosen.shape[0] == 0:
        return check
    bottom = np.full(check.shape[0], np.inf)
    np.minimum.at(bottom, labels[chosen], candidates.points[chosen, 2])
    foot = chosen[candidates.points[chosen, 2] <= bottom[labels[chosen]] + change_threshold]
    radius = max(BEHIND_MIN_RADIUS, SPARSE_PROBE_FACTOR * float(np.median(other.geometry.spacing)))
    below = level_surface_below(
        candidates.points[foot], other.geometry, ADJOINING_FACTOR * change_threshold, radius
    )
    standing = np.bincount(labels[foot], weights=below, minlength=check.shape[0])
    feet = np.bincount(labels[foot], minlength=check.shape[0])
    return check & (standing < 0.5 * feet)


def settled_coverage(
    candidates: Candidates,
    labels: NDArray[np.int64],
    radius: NDArray[np.float64],
    verdict: tuple[NDArray[np.bool_], NDArray[np.float64], NDArray[np.bool_]],
    hosts: NDArray[np.int64],
    clouds: tuple[NDArray[np.float64], LocalGeometry | None],
    change_threshold: float,
    faces: NDArray[np.bool_] | None = None,
) -> tuple[NDArray[np.bool_], NDArray[np.float64], int]:
    """The map test's ``verdict`` per part (coverage, confidence, seen round: shapes (parts,))
    with the fragments of coverage differences made ones
    (:func:`~app.core.localise.map_fragments.host_coverage`, ``hosts``), then the clusters in
    the other epoch's blind area (:func:`blind_clusters`, at the share as confidence, none with
    a change part in ``seen_around``; the unseen ``faces``, shape (parts,), are no blind
    surroundings), and how many parts those made so.  ``clouds``: this epoch's points (shape
    (n, 3)) and the other epoch's geometry (its isolated samples are no evidence of sight;
    None: every sample is)."""
    coverage, confidence = host_coverage(verdict[0], verdict[1], hosts)
    own_points, other = clouds
    blind, share = blind_clusters(
        own_points,
        candidates.index,
        radius,
        labels,
        coverage,
        change_threshold,
        verdict[2],
        faces,
        other,
    )
    made = blind & ~coverage
    return coverage | blind, np.where(made, share, confidence), int(made.sum())
