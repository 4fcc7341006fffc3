"""Visibility: unobserved is never change.  Change candidates become changed or unobserved.

With the other cloud's sensor origin, the ray test (:mod:`app.core.localise.rays`) says what
that sensor saw in each candidate's direction; with several stations, each station's own
returns are its rays and a candidate is observed when any station saw it.  A candidate whose
surface it saw only edge-on gets no evidence of its own; it is changed when connected to
candidates mostly seen through (a removed box's side face), unobserved otherwise.  Without an
origin, a coverage test: a candidate whose nearest point in the other cloud is farther than
``coverage_factor`` local spacings is unobserved (single-viewpoint scans should pass origins,
or their shadows' rims come out as changes); with ``origin_free_test="surfaces"`` the
surface test of :mod:`app.core.localise.origin_free` instead (merged clouds whose stations
are not known).  The default ``"auto"`` routes here: the surface test against a cloud the
pipeline found to be a merged lidar survey whose stations it could not recover
(``Side.stations_unknown``), the coverage test against any other cloud without origins.  A
cloud taken along a trajectory (``Side.trajectory_rays``) gives the trajectory test
(:mod:`app.core.localise.trajectory_visibility`): the ray test from its pseudo-stations.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.core.localise.distance import Side
from app.core.localise.gaps import in_sampling_gap
from app.core.localise.map_evidence import map_test
from app.core.localise.origin_free import surface_test
from app.core.localise.rays import (
    STATUS_EDGE_ON,
    STATUS_SEEN_THROUGH,
    STATUS_SURFACE,
    STATUS_UNOBSERVED,
    Candidates,
    RayTest,
    ray_visibility,
)
from app.core.localise.regions import (
    EVIDENCE_NO_COVERAGE,
    EVIDENCE_SEEN_EMPTY,
    cluster_labels,
)
from app.core.localise.trajectory_visibility import lone_sightings, trajectory_statuses

__all__ = [
    "LABEL_CHANGED",
    "LABEL_UNCHANGED",
    "LABEL_UNOBSERVED",
    "Labelled",
    "combine_station_status",
    "find_candidates",
    "label_candidates",
    "resolve_edge_on",
]

LABEL_UNCHANGED = 0
LABEL_CHANGED = 1
LABEL_UNOBSERVED = -1

EDGE_ON_SEEN_THROUGH_SHARE = 0.5
INDIRECT_CONFIDENCE = 0.5
"""Confidence of a change the test could not see directly: an edge-on face joined to faces
seen through, or a candidate the coverage test kept."""


@dataclass(frozen=True)
class Labelled:
    """One cloud's labels after the visibility test, and the evidence behind each.

    Attributes
    ----------
    label : ndarray, shape (n,), int8
        LABEL_UNCHANGED, LABEL_CHANGED or LABEL_UNOBSERVED.
    evidence : ndarray, shape (n,), int8
        :data:`~app.core.localise.regions.EVIDENCE_NAMES` code of each candidate (0 for
        points that were not candidates).
    confidence : ndarray, shape (n,), float32
        Confidence in each candidate's label, in [0, 1].
    report : dict
        JSON-serialisable figures of the test.
    """

    label: NDArray[np.int8]
    evidence: NDArray[np.int8]
    confidence: NDArray[np.float32]
    report: dict[str, Any]


LONE_SIGHTING_FACTOR = 1.5
"""A trajectory candidate within this many change thresholds of the other cloud's surface,
seen through by one pseudo-station while others saw it otherwise, is left to the edge-on
resolution (a rack's edge grazed by one stretch of the path)."""
MIN_STATION_POINTS = 10
"""A station of the other cloud with fewer returns than this is ignored (it saw nothing)."""


def find_candidates(
    side: Side, *, distance: NDArray[np.float64], candidate: NDArray[np.bool_]
) -> Candidates:
    """Gather ``side``'s candidates (before its neighbour index is released).

    Parameters
    ----------
    side : Side
    distance : ndarray, shape (n,)
        Each point's distance to the other cloud's surface.
    candidate : ndarray, shape (n,), bool

    Returns
    -------
    Candidates
    """
    index = np.flatnonzero(candidate)
    flattest = side.geometry.flattest_neighbour(index)
    return Candidates(
        index=index,
        points=side.points[index],
        normal=side.geometry.normal[flattest],
        linear=side.geometry.linear[flattest],
        spacing=side.geometry.spacing[index],
        surface_distance=distance[index],
    )


def label_candidates(
    own: Side,
    other: Side,
    *,
    candidates: Candidates,
    misalignment: float,
    threshold: float,
    settings: dict[str, Any],
    change_threshold: float | None = None,
) -> Labelled:
    """Label one cloud's points: candidates become changed or unobserved, the rest unchanged.

    Parameters
    ----------
    own : Side
        The cloud labelled.
    other : Side
        The other cloud: its sensor origin gives the ray visibility test, the coverage test
        is used without it.
    candidates : Candidates
        ``own``'s change candidates (:func:`find_candidates`).
    misalignment : float
        registration_rmse and the measured alignment residual combined (metres).
    threshold : float
        ``tau``: the sampling-gap test's tolerance (without origins).
    settings : dict
        Resolved keyword parameters.
    change_threshold : float, optional
        ``c``: a surface within it is the same surface (the map test); default ``threshold``.

    Returns
    -------
    Labelled
    """
    label = np.full(own.points.shape[0], LABEL_UNCHANGED, dtype=np.int8)
    evidence = np.zeros(own.points.shape[0], dtype=np.int8)
    confidence = np.zeros(own.points.shape[0], dtype=np.float32)
    index = candidates.index
    candidate_confidence = np.ones(index.shape[0], dtype=np.float32)
    candidate_evidence: NDArray[np.int8] | None = None
    side = own.name
    report: dict[str, Any] = {f"{side}_candidates": int(index.size)}
    origin_free_test = settings["origin_free_test"]
    if origin_free_test == "auto":  # the map test against any cloud without origins
        origin_free_test = "maps"
    if other.origins is None and origin_free_test == "maps":
        report[f"{side}_visibility"] = "maps"
        found = map_test(
            candidates,
            own=own,
            other=other,
            threshold=threshold,
            change_threshold=threshold if change_threshold is None else change_threshold,
            cluster_factor=settings["cluster_factor"],
        )
        status = found.status
        candidate_evidence = found.evidence
        candidate_confidence = found.confidence
        report.update({f"{side}_{name}": count for name, count in found.counts.items()})
    elif other.origins is None and origin_free_test == "surfaces":
        report[f"{side}_visibility"] = "surfaces"
        status, counts = surface_test(
            candidates,
            own=own,
            other=other,
            threshold=threshold,
            cluster_factor=settings["cluster_factor"],
        )
        report.update({f"{side}_{name}": count for name, count in counts.items()})
    elif other.origins is None:
        report[f"{side}_visibility"] = "coverage"
        covered = (
            own.nearest_distance[index]
            <= settings["coverage_factor"] * other.geometry.spacing[own.nearest_index[index]]
        )
        status = np.where(covered, STATUS_SEEN_THROUGH, STATUS_UNOBSERVED)
        candidate_confidence[:] = INDIRECT_CONFIDENCE
        if origin_free_test == "gaps":
            gap = in_sampling_gap(
                candidates.points,
                candidates.normal,
                own.nearest_distance[index],
                other=other.geometry,
                tolerance=threshold,
            )
            report[f"{side}_candidates_in_sampling_gaps"] = int(gap.sum())
            status = np.where(gap, STATUS_SURFACE, status)
    else:
        test = RayTest(
            normal_tolerance=settings["threshold_factor"]
            * math.hypot(own.geometry.noise, misalignment),
            range_tolerance=settings["threshold_factor"] * other.geometry.noise,
            margin_factor=settings["visibility_margin_factor"],
            angle_factor=settings["visibility_angle_factor"],
            beyond_fraction=settings["visibility_beyond_fraction"],
            miss_factor=settings["visibility_miss_factor"],
        )
        if other.trajectory_rays is not None and other.station is not None:
            report[f"{side}_visibility"] = "trajectory"
            statuses, figures = trajectory_statuses(candidates, own=own, other=other, test=test)
            status = combine_station_status(statuses)
            near = candidates.surface_distance < LONE_SIGHTING_FACTOR * (
                threshold if change_threshold is None else change_threshold
            )  # just past the change threshold: one ray through a grazed edge is not enough
            lone = lone_sightings(statuses) & (status == STATUS_SEEN_THROUGH) & near
            status = np.where(lone, STATUS_EDGE_ON, status).astype(np.int8)
            report[f"{side}_candidates_seen_through_once"] = int(lone.sum())
            report.update({f"{side}_other_{name}": value for name, value in figures.items()})
        else:
            report[f"{side}_visibility"] = "ray"
            status, steps = _any_station_status(candidates, own=own, other=other, test=test)
            report[f"{side}_other_stations"] = len(steps)
            report[f"{side}_other_angular_step_deg"] = math.degrees(float(np.median(steps)))
        report[f"{side}_candidates_on_other_surface"] = int((status == STATUS_SURFACE).sum())
        report[f"{side}_candidates_edge_on"] = int((status == STATUS_EDGE_ON).sum())
        direct = status == STATUS_SEEN_THROUGH
        status = resolve_edge_on(
            candidates.points,
            spacing=candidates.spacing,
            status=status,
            cluster_factor=settings["cluster_factor"],
        )
        candidate_confidence[~direct] = INDIRECT_CONFIDENCE
    if candidate_evidence is None:
        candidate_evidence = np.where(
            status == STATUS_UNOBSERVED, EVIDENCE_NO_COVERAGE, EVIDENCE_SEEN_EMPTY
        ).astype(np.int8)
    label[index[status == STATUS_SEEN_THROUGH]] = LABEL_CHANGED
    label[index[status == STATUS_UNOBSERVED]] = LABEL_UNOBSERVED
    judged = status != STATUS_SURFACE
    evidence[index[judged]] = candidate_evidence[judged]
    confidence[index[judged]] = candidate_confidence[judged]
    return Labelled(label=label, evidence=evidence, confidence=confidence, report=report)


def _any_station_status(
    candidates: Candidates, *, own: Side, other: Side, test: RayTest
) -> tuple[NDArray[np.int8], list[float]]:
    """Ray status of each candidate as seen by any station of the other cloud.

    Each station's rays are its own returns (``other.station``; all of them with one
    station), with their surfaces' normals; the statuses are combined by
    :func:`combine_station_status`.

    Returns
    -------
    status : ndarray, shape (c,), int8
    angular_steps : list of float
        Each station's typical angular step (radians).
    """
    assert other.origins is not None
    statuses = []
    angular_steps = []
    for number, origin in enumerate(other.origins):
        normal, linear = other.geometry.normal, other.geometry.linear
        if other.station is None:
            station_points = other.points
        else:
            mine = other.station == number
            station_points, normal, linear = other.points[mine], normal[mine], linear[mine]
        if station_points.shape[0] < MIN_STATION_POINTS:
            continue  # a station without returns saw nothing: all unobserved
        status, angular_step = ray_visibility(
            candidates,
            own=own.geometry,
            other_points=station_points,
            other_origin=origin,
            test=test,
            other_normals=normal,
            other_linear=linear,
        )
        statuses.append(status)
        angular_steps.append(angular_step)
    if not statuses:
        return np.full(candidates.index.shape[0], STATUS_UNOBSERVED, dtype=np.int8), [math.nan]
    return combine_station_status(np.stack(statuses)), angular_steps


def combine_station_status(statuses: NDArray[np.int8]) -> NDArray[np.int8]:
    """One status per candidate from each station's: observed by any station.

    Parameters
    ----------
    statuses : ndarray, shape (k, c), int8
        :func:`~app.core.localise.rays.ray_visibility` status from each of k stations.

    Returns
    -------
    ndarray, shape (c,), int8
        Seen through when at least one station saw through it and no more stations saw a
        surface there; else surface when a station saw one; else edge-on when a station saw
        its surface edge-on; else unobserved (no station could see it).  With k = 1 the
        station's own status.
    """
    if statuses.shape[0] == 1:
        return statuses[0]
    through = (statuses == STATUS_SEEN_THROUGH).sum(axis=0)
    surface = (statuses == STATUS_SURFACE).sum(axis=0)
    edge_on = (statuses == STATUS_EDGE_ON).any(axis=0)
    combined = np.where(edge_on, STATUS_EDGE_ON, STATUS_UNOBSERVED)
    combined = np.where(surface > 0, STATUS_SURFACE, combined)
    combined = np.where((through > 0) & (through >= surface), STATUS_SEEN_THROUGH, combined)
    return combined.astype(np.int8)


def resolve_edge_on(
    points: NDArray[np.float64],
    *,
    spacing: NDArray[np.float64],
    status: NDArray[np.int8],
    cluster_factor: float,
) -> NDArray[np.int8]:
    """Decide candidates whose surface the other sensor saw only edge-on.

    A removed box's face that the other sensor sees edge-on gets no ray evidence of its own,
    but the sensor saw through the rest of the box: edge-on candidates connected (within
    ``cluster_factor`` local spacings) to candidates that are mostly seen through are
    changed; the others (a pillar's face seen edge-on, the rest unchanged) are unobserved.

    Parameters
    ----------
    points : ndarray, shape (c, 3)
        The candidates.
    spacing : ndarray, shape (c,)
        Their cloud's local spacing.
    status : ndarray, shape (c,), int8
        From :func:`ray_visibility`.
    cluster_factor : float

    Returns
    -------
    ndarray, shape (c,), int8
        ``status`` with every STATUS_EDGE_ON replaced.
    """
    edge_on = status == STATUS_EDGE_ON
    if not edge_on.any():
        return status
    involved = np.flatnonzero(edge_on | (status == STATUS_SEEN_THROUGH))
    labels = cluster_labels(points[involved], cluster_factor * spacing[involved])
    seen_through_share = np.bincount(
        labels, weights=(status[involved] == STATUS_SEEN_THROUGH).astype(np.float64)
    ) / np.bincount(labels)
    promoted = seen_through_share[labels] >= EDGE_ON_SEEN_THROUGH_SHARE
    resolved = status.copy()
    resolved[involved] = np.where(
        edge_on[involved],
        np.where(promoted, STATUS_SEEN_THROUGH, STATUS_UNOBSERVED),
        status[involved],
    )
    return resolved
