"""Visibility: unobserved is never change.  Change candidates become changed or unobserved.

Each visibility test is a module of its own behind one small interface
(:mod:`app.core.localise.interface`); :func:`choose_test` picks one per cloud from what is
known of the other epoch's sensor, and the result reports which (``<side>_visibility``):

- its trajectory: the ray test from the pseudo-stations along the path
  (:mod:`app.core.localise.trajectory_visibility`, ``"trajectory"``);
- its origins (given, in the file, estimated or recovered; one per station): the ray test
  from each station (:mod:`app.core.localise.station_rays`, ``"ray"``);
- neither: ``origin_free_test`` chooses; by default (``"auto"``) the map test of fused maps
  (:mod:`app.core.localise.map_evidence`, ``"maps"``); ``"surfaces"`` the surface test of
  merged surveys (:mod:`app.core.localise.origin_free`); ``"coverage"`` and ``"gaps"`` the
  coverage test (:mod:`app.core.localise.coverage`).

Each candidate's evidence (seen_empty, no_coverage...) and confidence go with its label to
the regions.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.core.labels import LABEL_CHANGED, LABEL_UNCHANGED, LABEL_UNOBSERVED
from app.core.localise.coverage import CoverageTest
from app.core.localise.distance import Side
from app.core.localise.interface import FaceBorder, VisibilityContext, VisibilityTest
from app.core.localise.map_agreement import faces_meeting_changes
from app.core.localise.map_evidence import MapTest
from app.core.localise.map_scale import metric_planes
from app.core.localise.origin_free import SurfaceTest
from app.core.localise.rays import (
    STATUS_SEEN_THROUGH,
    STATUS_SURFACE,
    STATUS_UNOBSERVED,
    Candidates,
)
from app.core.localise.regions import EVIDENCE_NO_COVERAGE, EVIDENCE_SEEN_EMPTY
from app.core.localise.station_rays import (
    StationRayTest,
    combine_station_status,
    resolve_edge_on,
)
from app.core.localise.trajectory_visibility import TrajectoryTest
from app.core.threads import concurrently

__all__ = [
    "Labelled",
    "agree_on_faces",
    "choose_test",
    "combine_station_status",
    "find_candidates",
    "label_candidates",
    "resolve_edge_on",
]


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
    faces : FaceBorder, optional
        The map test's unseen faces (:func:`agree_on_faces`).
    """

    label: NDArray[np.int8]
    evidence: NDArray[np.int8]
    confidence: NDArray[np.float32]
    report: dict[str, Any]
    faces: FaceBorder | None = None


def find_candidates(
    side: Side, *, distance: NDArray[np.float64], candidate: NDArray[np.bool_], threads: int = 1
) -> Candidates:
    """Gather ``side``'s candidates (before its neighbour index is released).

    Parameters
    ----------
    side : Side
    distance : ndarray, shape (n,)
        Each point's distance to the other cloud's surface.
    candidate : ndarray, shape (n,), bool
    threads : int
        Threads that find the candidates' flattest neighbours (the same ones on any number).

    Returns
    -------
    Candidates
    """
    index = np.flatnonzero(candidate)
    flattest = side.geometry.flattest_neighbour(index, threads)
    return Candidates(
        index=index,
        points=side.points[index],
        normal=side.geometry.normal[flattest],
        linear=side.geometry.linear[flattest],
        spacing=side.geometry.spacing[index],
        surface_distance=distance[index],
    )


def choose_test(other: Side, settings: Mapping[str, Any]) -> VisibilityTest:
    """The visibility test for candidates seen from ``other``'s epoch.

    The other cloud's trajectory gives the trajectory test, its origins the ray test from its
    stations; without either, ``origin_free_test`` chooses (``"auto"``: the map test).
    """
    if other.origins is not None:
        if other.trajectory_rays is not None and other.station is not None:
            return TrajectoryTest()
        return StationRayTest()
    chosen = settings["origin_free_test"]
    if chosen in ("auto", "maps"):
        return MapTest()
    if chosen == "surfaces":
        return SurfaceTest()
    return CoverageTest(sampling_gaps=chosen == "gaps")


def map_test_planes(
    sides: tuple[Side, Side], settings: Mapping[str, Any], threads: int
) -> dict[str, Any] | None:
    """The map test's metric-scale planes of both clouds by name (None per cloud that is not
    dense), fitted once and concurrently when either cloud's candidates get the map test (each
    cloud's map test reads both clouds' planes); None when neither does."""
    reference_side, scan_side = sides
    if not any(choose_test(other, settings).name == MapTest.name for other in sides):
        return None
    planes = concurrently(
        threads, lambda: metric_planes(reference_side), lambda: metric_planes(scan_side)
    )
    return dict(zip((reference_side.name, scan_side.name), planes, strict=True))


def label_candidates(
    own: Side,
    other: Side,
    *,
    candidates: Candidates,
    misalignment: float,
    threshold: float,
    settings: dict[str, Any],
    change_threshold: float | None = None,
    threads: int = 1,
    shared: Mapping[str, Any] | None = None,
) -> Labelled:
    """Label one cloud's points: candidates become changed or unobserved, the rest unchanged.

    Parameters
    ----------
    own : Side
        The cloud labelled.
    other : Side
        The other cloud: what is known of its sensor (:func:`choose_test`) picks the test.
    candidates : Candidates
        ``own``'s change candidates (:func:`find_candidates`).
    misalignment : float
        registration_rmse and the measured alignment residual combined (metres).
    threshold : float
        ``tau``: the plane tolerance (metres).
    settings : dict
        Resolved keyword parameters.
    change_threshold : float, optional
        ``c``: a surface within it is the same surface; default ``threshold``.
    threads : int
        Threads the test may keep busy (the same labels on any number).
    shared : mapping, optional
        What the tests compute once per comparison (:func:`map_test_planes`).

    Returns
    -------
    Labelled
    """
    test = choose_test(other, settings)
    context = VisibilityContext(
        misalignment=misalignment,
        threshold=threshold,
        change_threshold=threshold if change_threshold is None else change_threshold,
        settings=settings,
        threads=threads,
        shared=shared,
    )
    outcome = test(candidates, own=own, other=other, context=context)
    status = outcome.status
    side = own.name
    report: dict[str, Any] = {f"{side}_candidates": int(candidates.index.size)}
    report[f"{side}_visibility"] = test.name
    report.update({f"{side}_{name}": value for name, value in outcome.report.items()})
    evidence_of_candidates = outcome.evidence
    if evidence_of_candidates is None:
        evidence_of_candidates = np.where(
            status == STATUS_UNOBSERVED, EVIDENCE_NO_COVERAGE, EVIDENCE_SEEN_EMPTY
        ).astype(np.int8)
    label = np.full(own.points.shape[0], LABEL_UNCHANGED, dtype=np.int8)
    evidence = np.zeros(own.points.shape[0], dtype=np.int8)
    confidence = np.zeros(own.points.shape[0], dtype=np.float32)
    index = candidates.index
    label[index[status == STATUS_SEEN_THROUGH]] = LABEL_CHANGED
    label[index[status == STATUS_UNOBSERVED]] = LABEL_UNOBSERVED
    judged = status != STATUS_SURFACE
    evidence[index[judged]] = evidence_of_candidates[judged]
    confidence[index[judged]] = outcome.confidence[judged]
    return Labelled(
        label=label, evidence=evidence, confidence=confidence, report=report, faces=outcome.faces
    )


def agree_on_faces(
    sides: tuple[Side, Side],
    labelled: tuple[Labelled, Labelled],
    *,
    threshold: float,
    change_threshold: float,
) -> tuple[Labelled, Labelled]:
    """Both sides' labels with each side's unseen faces that meet a change of the other
    epoch made changes (:func:`~app.core.localise.map_agreement.faces_meeting_changes`, from both
    sides' first labels); ``threshold`` and ``change_threshold`` are ``tau`` and ``c``
    (metres)."""
    found = faces_meeting_changes(
        sides,
        (labelled[0].label, labelled[1].label),
        (labelled[0].faces, labelled[1].faces),
        tolerance=threshold,
        change_threshold=change_threshold,
    )
    agreed = []
    for side, own, (chosen, share) in zip(sides, labelled, found, strict=True):
        label, evidence, confidence = own.label.copy(), own.evidence.copy(), own.confidence.copy()
        label[chosen] = LABEL_CHANGED
        evidence[chosen] = EVIDENCE_SEEN_EMPTY
        confidence[chosen] = share
        report = {**own.report, f"{side.name}_map_faces_meeting_changes": int(chosen.shape[0])}
        agreed.append(
            dataclasses.replace(
                own, label=label, evidence=evidence, confidence=confidence, report=report
            )
        )
    return agreed[0], agreed[1]
