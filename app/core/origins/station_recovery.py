"""Recover the stations of a cloud merged from several lidar stations, from the points alone.

An upright spinning lidar fires each column (one azimuth, every ring) in a vertical half-plane
through its axis, and range noise moves a return along its ray, inside that plane: in the top
view, two neighbouring returns of one column lie on a line through the station's (x, y)
exactly.  Neighbour pairs of a merged cloud give many lines; those of each station's columns
concur at its (x, y), the rest (ring pairs, pairs across stations) scatter.  So:

1. **Top view** (:func:`~app.core.origins.concurrence.column_centres`): a Hough vote of the
   pair lines on a fine 2 cm grid (a line does not vote near its own pair, where dense returns
   would pile votes up), then each of the strongest peaks is refined to the point the most
   lines pass within a millimetre or two of, and kept when its concurring lines exceed those
   passing by chance (estimated from the lines passing a little farther) by many standard
   deviations.
2. **Height** (:func:`station_height`): from the right origin a lidar's returns lie on a few
   cones of fixed elevation (its rings); the height whose elevation histogram is sharpest,
   coarse then fine, is the station's.
3. **Acceptance**: a station is kept when many points lie on its rings
   (:func:`~app.core.localise.station_assignment.ring_contrast`).
4. **Again on the rest** (:func:`recover_stations`): the points on a kept station's rings are
   removed and the search is repeated on the others, until a pass finds nothing: stations
   standing close together interleave their returns, so that few neighbour pairs of one
   station's columns are left until the other stations' returns are gone.
5. **The clearest only** (:func:`clearest_stations`): a station found a few centimetres beside
   a true one (on a later pass, from the true one's returns that its rings left over) sees the
   true one's rings a little blurred; it is dropped when it is the sharpest explanation of too
   few of the points on its rings.

A cloud with two or more kept stations was not taken from one place; its points are then
assigned to the stations (:func:`~app.core.localise.station_assignment.assign_stations`).
Every random choice is seeded (``random_state``): the same cloud gives the same stations.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.core.cloud import PointCloud
from app.core.errors import InputError
from app.core.localise.station_assignment import (
    RING_CONTRAST,
    STATION_INDEX_ATTRIBUTE,
    ring_contrast,
)
from app.core.origins.concurrence import MAX_STATIONS, column_centres, search_centres
from app.core.origins.known_stations import estimate_each_station
from app.core.origins.resolve import STATIONS_UNKNOWN, ResolvedOrigin, resolve_origin
from app.core.origins.sampling import LidarSampling, lidar_sampling
from app.core.origins.station_height import station_height
from app.core.origins.voxels import whole_voxels

__all__ = [
    "RECOVER_CHOICES",
    "RecoveredStations",
    "as_recover_setting",
    "clearest_stations",
    "column_centres",
    "recover_stations",
    "recovered_before_apex",
    "resolve_stations",
    "station_height",
]

MAX_POINTS = 200_000
"""Points used (a seeded random subset of whole voxels beyond this): lines need lattice
neighbours.  The lines, Hough and tests after it cost the same whatever the cloud's size; at
1M points a scan 200k whole voxels find every station as 300k did, 10-30 % sooner."""
MAX_PASSES = 4
"""Searches: each after removing the points that the stations found so far explain."""
MIN_RING_SHARE = 0.05
"""A recovered station is kept when at least this share of the points (and MIN_RING_POINTS)
lie on its rings."""
MIN_RING_POINTS = 500
MIN_RESIDUAL_POINTS = 5_000
"""No further search on fewer points than this left unexplained."""
MIN_CLEAREST_SHARE = 0.3
"""A recovered station is kept when, of the points on its rings, at least this share lie on
them more clearly (higher ring contrast) than on any other station's.  True stations: 0.84-0.98
on synthetic surveys of 1-4M points (three stations 0.3-1.5 m apart: 0.90-0.98), 0.37-0.78 on
the whole voxels of a 100M-point one (rings 0.043 degrees apart); stations found 7-17 cm beside
a true one there: 0.17-0.20."""


@dataclass(frozen=True)
class RecoveredStations:
    """Stations recovered from a cloud.

    Attributes
    ----------
    origins : ndarray, shape (k, 3)
        Kept stations, in the order found (k may be 0 or 1).
    ring_share : ndarray, shape (k,)
        Share of the cloud's points on each station's rings (its confidence).
    concurring_lines : ndarray, shape (k,), int64
        Top-view lines through each station.
    n_lines : int
        Lines of all passes.
    passes : int
        Searches made (the first on all points, each next one on the points left unexplained).
    """

    origins: NDArray[np.float64]
    ring_share: NDArray[np.float64]
    concurring_lines: NDArray[np.int64]
    n_lines: int
    passes: int = 1

    @property
    def several(self) -> bool:
        """The cloud was taken from two or more places."""
        return self.origins.shape[0] >= 2


def search_subset(
    points: NDArray[np.float64], random_state: int | np.random.Generator | None
) -> tuple[NDArray[np.float64], np.random.Generator]:
    """The points :func:`recover_stations` searches (whole voxels, :data:`MAX_POINTS`) and its
    generator after drawing them: the same points and seed give the same ones.

    Returns
    -------
    subset : ndarray, shape (m, 3)
    rng : numpy.random.Generator
    """
    rng = np.random.default_rng(random_state)
    return whole_voxels(np.asarray(points, dtype=np.float64), MAX_POINTS, rng), rng


def recover_stations(
    points: NDArray[np.float64],
    *,
    random_state: int | np.random.Generator | None = 0,
    drawn: tuple[NDArray[np.float64], np.random.Generator] | None = None,
) -> RecoveredStations:
    """The lidar stations a cloud was merged from (upright spinning lidars).

    Searches are repeated on the points left unexplained: after each one, the points lying on
    a kept station's rings (elevation bins far above the background, seen from its origin) are
    removed, which leaves the returns of stations standing close to it (whose neighbour pairs
    were mixed with its own) with neighbours of their own.  Seeded: the same points and
    ``random_state`` give the same stations.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        The cloud, in a frame whose z axis is vertical.
    random_state : int, Generator or None
    drawn : tuple, optional
        :func:`search_subset`'s answer for ``points`` and ``random_state``, already drawn.

    Returns
    -------
    RecoveredStations
        Possibly none (no lidar structure) or one (a single-station cloud).
    """
    subset, rng = search_subset(points, random_state) if drawn is None else drawn
    unexplained = np.ones(subset.shape[0], dtype=bool)
    origins: list[NDArray[np.float64]] = []
    shares: list[float] = []
    supports: list[int] = []
    contrasts: list[NDArray[np.float64]] = []
    passes = 0
    n_lines = 0
    while passes < MAX_PASSES and len(origins) < MAX_STATIONS:
        residual = subset[unexplained]
        if residual.shape[0] < MIN_RESIDUAL_POINTS:
            break
        passes += 1
        known = np.array([origin[:2] for origin in origins]).reshape(-1, 2)
        found = 0
        centres, lines = search_centres(residual, rng, known)
        n_lines += lines
        for centre, support in centres:
            height = station_height(residual, centre, rng)
            origin = np.array([centre[0], centre[1], height])
            contrast = ring_contrast(subset, origin)
            on_rings = contrast >= RING_CONTRAST
            share = float(on_rings.mean())
            if share >= MIN_RING_SHARE and on_rings.sum() >= MIN_RING_POINTS:
                origins.append(origin)
                shares.append(share)
                supports.append(support)
                contrasts.append(contrast)
                unexplained &= ~on_rings
                found += 1
                if len(origins) >= MAX_STATIONS:
                    break
        if found == 0:
            break
    kept = clearest_stations(np.array(contrasts).reshape(-1, subset.shape[0]))
    return RecoveredStations(
        origins=np.array(origins, dtype=np.float64).reshape(-1, 3)[kept],
        ring_share=np.array(shares, dtype=np.float64)[kept],
        concurring_lines=np.array(supports, dtype=np.int64)[kept],
        n_lines=n_lines,
        passes=passes,
    )


def clearest_stations(contrast: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Which recovered stations to keep: those that are the clearest explanation of enough of
    the points on their rings.

    The station whose share of points on its rings that lie on them more clearly than on any
    other kept station's is the lowest is dropped while that share is under
    :data:`MIN_CLEAREST_SHARE`, and the shares are counted again without it (the points it
    took go back to the others).

    Parameters
    ----------
    contrast : ndarray, shape (k, n)
        Ring contrast of each point seen from each station
        (:func:`~app.core.localise.station_assignment.ring_contrast`).

    Returns
    -------
    ndarray, shape (k,), bool
    """
    keep = np.ones(contrast.shape[0], dtype=bool)
    while keep.sum() >= 2:
        stations = np.flatnonzero(keep)
        kept_contrast = contrast[stations]
        on_rings = kept_contrast >= RING_CONTRAST
        clearest = kept_contrast.argmax(axis=0)
        shares = np.array(
            [
                np.count_nonzero(on_rings[number] & (clearest == number))
                / max(1, np.count_nonzero(on_rings[number]))
                for number in range(stations.size)
            ]
        )
        weakest = int(np.argmin(shares))
        if shares[weakest] >= MIN_CLEAREST_SHARE:
            break
        keep[stations[weakest]] = False
    return keep


RECOVER_CHOICES = (True, False, "auto")
"""Values of the ``recover_stations`` comparison parameter: recover the stations of a cloud
left without an origin always, never, or (``"auto"``, the default) when its sampling is a
lidar's (:func:`~app.core.origins.sampling.lidar_sampling`)."""


def as_recover_setting(value: Any) -> bool | str:
    """The ``recover_stations`` parameter checked: True, False or ``"auto"``.

    Raises
    ------
    InputError
        Any other value.
    """
    if isinstance(value, bool) or value == "auto":
        return value
    raise InputError(
        "recover_stations must be true (always recover the stations of a cloud left without "
        'an origin), false (never) or "auto" (when its sampling is a lidar\'s: the default), '
        f"got {value!r}"
    )


MIN_EXPLAINED_SHARE = 0.5
"""Stations recovered are used when their rings hold at least this share of the points
together (merged synthetic surveys: 1.00-1.08; three Hough artefacts in a real Velodyne frame
without its ground, which one origin explains once the apex is searched: 0.21)."""


def resolve_stations(
    side: str,
    points: NDArray[np.float64],
    *,
    given: NDArray[np.float64] | None,
    from_file: NDArray[np.float64] | None,
    estimate: bool,
    recover: bool | str,
    random_state: int = 0,
    station_of: PointCloud | None = None,
    resolved: ResolvedOrigin | None = None,
    early: EarlySearch | None = None,
) -> ResolvedOrigin:
    """The origin(s) of one cloud: several given, or one resolved, or stations recovered.

    Several given origins (a merged survey's stations), or several from the file (an E57
    file's scans, per-point origin fields) when none are given, are used as they are.  One
    origin (given, from the file or estimated) goes through
    :func:`~app.core.origins.resolve.resolve_origin`.  When that leaves the cloud without an
    origin, its stations are recovered (:func:`recover_stations`) and used when there are
    several: with ``recover=True`` always, with ``"auto"`` only when its sampling is a
    lidar's (:func:`~app.core.origins.sampling.lidar_sampling`; uniform, random or gridded
    clouds do not pay the search).  A lidar cloud that no single origin explains and whose
    stations are not recovered is reported as such (``stations_unknown``: the localiser then
    uses the origin-free surface test for it) with a warning.  Stations are used only when
    their rings hold :data:`MIN_EXPLAINED_SHARE` of the points together.

    With ``recover=True`` and no origin given or in the file, the estimate's apex search
    (:mod:`~app.core.origins.apex`) waits until the recovery has found fewer than two
    stations: a merged survey does not pay for it.  With ``"auto"`` it comes first: a
    single station that only the apex search finds (a frame without its ground) is never
    taken for a merged survey.

    Parameters
    ----------
    side : str
    points : ndarray, shape (n, 3)
        In the frame the origins are used in (z up).
    given : ndarray, shape (k, 3), or None
    from_file : ndarray, shape (3,) or (k, 3), or None
    estimate : bool
    recover : {True, False, "auto"}
    random_state : int
    station_of : PointCloud, optional
        The cloud ``points`` come from (in its order): its ``station_index`` attribute, if any,
        says which station took each point.  With no origin given or in the file and several
        stations, each station's origin is estimated from its own points
        (:func:`estimate_each_station`).
    resolved : ResolvedOrigin, optional
        This cloud's resolution already made with ``recover=False`` (and the same other
        arguments): only the stations are searched (:mod:`~app.core.origins.own_frame` tries
        the cloud's own frame before that).
    early : tuple, optional
        :func:`recovered_before_apex`'s answer for these points and ``random_state``, already
        had by the caller: its sampling and stations are used instead of being measured again.

    Returns
    -------
    ResolvedOrigin
        ``origin`` of shape (k, 3) with k >= 2 for several stations, else as
        :func:`~app.core.origins.resolve.resolve_origin` gives it; its evidence says whether
        the sampling was measured (``lidar_*``) and the stations searched
        (``stations_recovered``).
    """
    if resolved is None:
        if given is not None and len(given) > 1:
            return ResolvedOrigin(given, "given", None)
        if from_file is not None and np.asarray(from_file).size > 3:
            if given is None:
                return ResolvedOrigin(np.asarray(from_file).reshape(-1, 3), "file", None)
            from_file = None  # one given origin overrides the file's stations
        station = None if station_of is None else station_of.attributes.get(STATION_INDEX_ATTRIBUTE)
        if given is None and from_file is None and estimate and station is not None:
            each = estimate_each_station(side, points, station, random_state)
            if each is not None:
                return each
    # nothing to check: an estimate that fails the column and ring signals is taken for a
    # merged survey, whose stations are recovered before the costly apex search is tried
    recover_first = recover is True and given is None and from_file is None and resolved is None
    options = {
        "given": None if given is None else given[0],
        "from_file": None if from_file is None else np.asarray(from_file).reshape(3),
        "estimate": estimate,
        "random_state": random_state,
    }
    if (
        early is None
        and resolved is None
        and recover == "auto"
        and given is None
        and (from_file is None and estimate)
    ):
        early = recovered_before_apex(side, points, options, random_state, station_of=station_of)
        if early is not None and early[0].origin is not None:
            return early[0]
    if resolved is None:
        resolved = resolve_origin(side, points, apex=not recover_first, **options)
    if resolved.origin is not None or recover is False:
        return resolved
    # an estimate was made and no single origin explains the cloud (not merely left undone)
    not_one_station = "ring_share" in resolved.evidence
    if recover == "auto" and not not_one_station:
        return resolved
    # the same points and seed: the same sampling and stations as before the apex search
    if early is not None and early[1] is not None:
        sampling = early[1]
    else:
        sampling = measured_sampling(points, station_of, random_state)
    evidence = {**resolved.evidence, **sampling.evidence()}
    if recover == "auto" and not sampling.lidar_like:
        return dataclasses.replace(resolved, evidence=evidence)
    if early is not None and early[2] is not None:
        found = early[2]
    else:
        found = recover_stations(search_points(points, station_of), random_state=random_state)
    evidence["stations_recovered"] = float(found.origins.shape[0])
    explained = float(found.ring_share.sum())
    evidence["stations_explained_share"] = round(explained, 3)
    if found.several and explained >= MIN_EXPLAINED_SHARE:
        return _recovered(found, resolved.warnings, evidence)
    if recover_first and estimate:  # one station after all: the full estimate
        resolved = resolve_origin(side, points, **options)
        if resolved.origin is not None:
            return resolved
        evidence = {**resolved.evidence, **evidence}
        not_one_station = "ring_share" in resolved.evidence
    warnings = list(resolved.warnings)
    if sampling.lidar_like and not_one_station:
        evidence[STATIONS_UNKNOWN] = 1.0
        warnings.append(
            f"the {side} was sampled by a lidar but no single sensor origin explains it (a "
            "cloud merged from several stations?), and its stations could not be recovered "
            f"(found {found.origins.shape[0]}); changes against it were told apart without "
            "origins (origin-free surface test): give each station's origin for the ray test"
        )
    return dataclasses.replace(resolved, warnings=warnings, evidence=evidence)


def measured_sampling(
    points: NDArray[np.float64], cloud: PointCloud | None, random_state: int
) -> LidarSampling:
    """:func:`~app.core.origins.sampling.lidar_sampling` of the cloud ``points`` come from:
    its full-density ``sampling_points`` when ``points`` is a subsample of it (a streamed
    comparison's: a subsample thins a lidar's rings, and its twins with them), else
    ``points``."""
    if cloud is not None and cloud.sampling_points is not None:
        return lidar_sampling(cloud.sampling_points, random_state=random_state)
    return lidar_sampling(points, random_state=random_state)


def search_points(points: NDArray[np.float64], cloud: PointCloud | None) -> NDArray[np.float64]:
    """What the stations are searched on: the cloud's full-density ``sampling_points`` when
    ``points`` is a subsample of it (a streamed comparison's, in the frame of ``points``: at
    100M points a 2 % subsample keeps too few pairs of one column to find any station), else
    ``points``."""
    if cloud is not None and cloud.sampling_points is not None:
        return np.asarray(cloud.sampling_points, dtype=np.float64)
    return points


EARLY_MAX_STATION_SHARE = 0.7
"""Stations recovered before the estimate's sharpening and apex search are used at once only
when no one of them holds this share of the points (merged synthetic surveys: 0.1-0.5 each): a
single station that the apex search would find holds 0.8-1 of its cloud, so a cloud one of
whose recovered stations holds that much waits for the full estimate."""


def _recovered(
    found: RecoveredStations, warnings: list[str], evidence: dict[str, float]
) -> ResolvedOrigin:
    """The recovered stations as the cloud's origins."""
    return ResolvedOrigin(
        found.origins,
        "recovered",
        None,
        warnings,
        evidence,
        station_confidence=[round(float(share), 3) for share in found.ring_share],
    )


EarlySearch = tuple[ResolvedOrigin, Any, RecoveredStations | None]
""":func:`recovered_before_apex`'s answer: the resolution, the sampling, the stations."""


STATIONS_FIRST = "stations_first"
"""Evidence entry (1.0) of stations recovered before any single-origin estimate was made
(:func:`recovered_before_apex` with ``stations_first``)."""


SURE_SINGLE_CONFIDENCE = 0.8
"""A single origin estimated with less confidence than this (but at least
:data:`~app.core.origins.estimate.CONFIDENT`) may be one station of a merged survey: one of
two stations that took half the points each passes the estimate at 0.52-0.57 (TLS scenes 000
and 104), a single lidar's frame scores 1.0 (KITTI); its cloud's stations are searched too."""


def _stations_instead(
    kept: ResolvedOrigin,
    quick: ResolvedOrigin,
    points: NDArray[np.float64],
    random_state: int,
    station_of: PointCloud | None,
    searched: tuple[LidarSampling | None, RecoveredStations | None],
    evidence: dict[str, float],
) -> EarlySearch:
    """The cloud's recovered stations when it is lidar-like and they qualify
    (:func:`_early_enough`: several, explaining the cloud together, none of them most of it,
    which a single station's cloud never gives), with ``quick``'s evidence and warnings and
    ``evidence`` added; else ``kept``.  ``searched``: the sampling and stations already
    measured and searched on these points (None: not yet; the same points and seed give the
    same ones).  A ``kept`` origin whose rings hold most of the points
    (:func:`one_station_explains`) is kept without the search: the stations could not qualify."""
    sampling, found = searched
    drawn = None
    if found is None and kept.origin is not None:
        drawn = search_subset(search_points(points, station_of), random_state)
        if one_station_explains(drawn[0], kept.origin):
            return kept, sampling, None
    if sampling is None:
        sampling = measured_sampling(points, station_of, random_state)
    if not sampling.lidar_like:
        return kept, sampling, None
    if found is None:
        found = recover_stations(
            search_points(points, station_of), random_state=random_state, drawn=drawn
        )
    if not _early_enough(found):
        return kept, sampling, found
    evidence = {**quick.evidence, **_recovered_evidence(found, sampling), **evidence}
    return _recovered(found, quick.warnings, evidence), sampling, found


def one_station_explains(subset: NDArray[np.float64], origin: NDArray[np.float64]) -> bool:
    """Whether the rings seen from ``origin`` hold at least :data:`EARLY_MAX_STATION_SHARE` of
    ``subset`` (:func:`search_subset`'s points), as one station's rings hold its cloud.

    Stations recovered from such a cloud never qualify (:func:`_early_enough`: none of them may
    hold that share), so a weak single estimate there is kept without the search (the held-out
    1M single-station scan: 0.97, 0.4 CPU s of search saved; one of two stations that took
    half a TLS survey each: about a half).

    Parameters
    ----------
    subset : ndarray, shape (m, 3)
    origin : ndarray, shape (3,)
    """
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    on_rings = ring_contrast(subset, origin) >= RING_CONTRAST
    return bool(on_rings.mean() >= EARLY_MAX_STATION_SHARE) if subset.shape[0] else False


WEAK_SINGLE = "weak_single_confidence"
"""Evidence entry: the confidence of the single origin estimated before the stations that
replaced it were recovered (:func:`recovered_before_apex`)."""


def _early_enough(found: RecoveredStations) -> bool:
    """Several stations that together explain the cloud, none of them most of it."""
    return (
        found.several
        and float(found.ring_share.sum()) >= MIN_EXPLAINED_SHARE
        and float(found.ring_share.max()) < EARLY_MAX_STATION_SHARE
    )


def _recovered_evidence(found: RecoveredStations, sampling: LidarSampling) -> dict[str, float]:
    """Evidence entries of recovered stations and the sampling that let them be searched."""
    return {
        **sampling.evidence(),
        "stations_recovered": float(found.origins.shape[0]),
        "stations_explained_share": round(float(found.ring_share.sum()), 3),
    }


def recovered_before_apex(
    side: str,
    points: NDArray[np.float64],
    options: dict[str, Any],
    random_state: int,
    *,
    stations_first: bool = False,
    station_of: PointCloud | None = None,
) -> EarlySearch | None:
    """With ``recover="auto"``: the stations of a merged survey, before the apex search.

    The estimate without its apex search (and without the sharpening that only the apex
    search's allowance triggers) is the full estimate whenever it is confident, so it is
    returned then.  Otherwise, on a lidar cloud, the stations are recovered: several that
    together explain :data:`MIN_EXPLAINED_SHARE` of the points, none of them
    :data:`EARLY_MAX_STATION_SHARE`, are returned without the sharpening and apex search
    (0.5-0.7 s at 1M points that a merged survey never gains from).  Else the full estimate
    is still to be made; the sampling and stations found (the same points and seed give the
    same ones) are returned for the rest of :func:`resolve_stations`.

    With ``stations_first`` (the other epoch was a merged survey: a site surveyed from several
    stations is surveyed so again), the stations of a lidar cloud are searched before the
    single-origin estimate, which is skipped when they qualify as above (0.2-0.3 s at 1M
    points); else the estimate follows and the search is not made again.

    Returns
    -------
    (ResolvedOrigin, LidarSampling or None, RecoveredStations or None) or None
        The resolution (its ``origin`` None when the full estimate is still to be made), the
        sampling and the stations when measured and searched; None when no estimate was made.
    """
    sampling = found = None
    if stations_first:
        sampling = measured_sampling(points, station_of, random_state)
        if sampling.lidar_like:
            found = recover_stations(search_points(points, station_of), random_state=random_state)
            if _early_enough(found):
                evidence = {**_recovered_evidence(found, sampling), STATIONS_FIRST: 1.0}
                return _recovered(found, [], evidence), sampling, found
    quick = resolve_origin(side, points, apex=False, **options)
    searched = (sampling, found)
    if quick.origin is not None:
        confidence = quick.confidence
        sure = confidence is None or confidence >= SURE_SINGLE_CONFIDENCE
        if quick.source != "estimated" or sure:
            return quick, None, None
        weak = {WEAK_SINGLE: confidence}  # perhaps one station of a merged survey
        return _stations_instead(quick, quick, points, random_state, station_of, searched, weak)
    if "ring_share" not in quick.evidence:
        return None
    undecided = ResolvedOrigin(None, None, None)
    return _stations_instead(undecided, quick, points, random_state, station_of, searched, {})
