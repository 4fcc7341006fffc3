"""Stage 5, **decide**: the paper's global score between the parts of both clouds that both
sensors observed, then the decision rule (:mod:`app.core.site_calibration`).

Points the other scan could not see are not evidence of change, so the detector compares the
mutually observed points (all of them when fewer than :data:`app.core.cloud.MIN_POINTS` are);
its threshold is calibrated from the clouds' own resampling noise
(:mod:`app.core.detectors`).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import threadpool_limits

from app.core.cloud import MIN_POINTS
from app.core.comparison.reports import Decision, DecisionTest, SiteProvenance
from app.core.detectors.base import ChangeDetector, Detection
from app.core.labels import LABEL_UNOBSERVED
from app.core.localise import ChangedRegion, Localisation
from app.core.site_calibration import DecisionInputs, decide, largest_extent


@dataclass(frozen=True)
class Detected:
    """The detector's outcome and which points it compared.

    Attributes
    ----------
    detection : Detection
        Score, calibrated threshold, the detector's own verdict and its calibration.
    compared_points : {"mutually observed", "all"}
    """

    detection: Detection
    compared_points: str


def detect_change(
    detector: ChangeDetector,
    reference_points: NDArray[np.float64],
    aligned_scan: NDArray[np.float64],
    localisation: Localisation,
    *,
    sample_points: int | None = None,
    random_state: int = 0,
) -> Detected:
    """The detector's score on the mutually observed points (one BLAS thread).

    Parameters
    ----------
    detector : ChangeDetector
    reference_points : ndarray, shape (n, 3)
    aligned_scan : ndarray, shape (m, 3)
    localisation : Localisation
        Of these points: its labels say which are observed.
    sample_points : int, optional
        Score at most this many points of each cloud, a uniform random subsample (seeded by
        ``random_state``) of those it would score (a tiled comparison's bound on memory); the
        detectors thin their input on a voxel grid to a few thousand working points anyway.
        None: every one.
    random_state : int

    Returns
    -------
    Detected
    """
    return detect_observed(
        detector,
        reference_points,
        aligned_scan,
        (
            localisation.reference_label != LABEL_UNOBSERVED,
            localisation.scan_label != LABEL_UNOBSERVED,
        ),
        sample_points=sample_points,
        random_state=random_state,
    )


def detect_observed(
    detector: ChangeDetector,
    reference_points: NDArray[np.float64],
    aligned_scan: NDArray[np.float64],
    observed: tuple[NDArray[np.bool_], NDArray[np.bool_]],
    *,
    sample_points: int | None = None,
    random_state: int = 0,
) -> Detected:
    """:func:`detect_change` given which points are observed (the localisation's labels are
    not needed: only which points are unobserved, known before its regions are).

    Parameters
    ----------
    detector : ChangeDetector
    reference_points : ndarray, shape (n, 3)
    aligned_scan : ndarray, shape (m, 3)
    observed : (ndarray, ndarray), shapes (n,) and (m,), bool
        Each cloud's points not labelled unobserved.
    sample_points : int, optional
    random_state : int
        As in :func:`detect_change`.

    Returns
    -------
    Detected
    """
    reference_observed, scan_observed = observed
    use_observed = (
        np.count_nonzero(reference_observed) >= MIN_POINTS
        and np.count_nonzero(scan_observed) >= MIN_POINTS
    )
    compared = "mutually observed" if use_observed else "all"
    if sample_points is not None:
        return _detect_sample(
            detector,
            (reference_points, reference_observed if use_observed else None),
            (aligned_scan, scan_observed if use_observed else None),
            sample_points,
            random_state,
            compared,
        )
    with threadpool_limits(limits=1, user_api="blas"):
        if use_observed:
            detection = detector.detect(
                reference_points[reference_observed], aligned_scan[scan_observed]
            )
        else:
            detection = detector.detect(reference_points, aligned_scan)
    return Detected(detection, compared)


class DetectionAhead:
    """:func:`detect_observed` on a thread of its own, started as soon as the localiser knows
    which points are observed (``localise_changes(on_observed=ahead.start)``), so the score is
    computed beside the region clustering instead of after it.  The same result.

    Parameters
    ----------
    detector : ChangeDetector
    reference_points : ndarray, shape (n, 3)
    aligned_scan : ndarray, shape (m, 3)
    """

    def __init__(
        self,
        detector: ChangeDetector,
        reference_points: NDArray[np.float64],
        aligned_scan: NDArray[np.float64],
    ):
        self._clouds = (detector, reference_points, aligned_scan)
        self._thread: threading.Thread | None = None
        self._result: Detected | None = None
        self._error: BaseException | None = None
        self.seconds = 0.0
        """Wall seconds the detection took on its thread."""

    def start(
        self, reference_observed: NDArray[np.bool_], scan_observed: NDArray[np.bool_]
    ) -> None:
        """Start the detection of these observed points, shapes (n,) and (m,) (once)."""
        if self._thread is not None:
            raise RuntimeError("the detection ahead was started already")
        self._thread = threading.Thread(
            target=self._run, args=((reference_observed, scan_observed),), name="detection"
        )
        self._thread.start()

    def _run(self, observed: tuple[NDArray[np.bool_], NDArray[np.bool_]]) -> None:
        started = time.perf_counter()
        try:
            self._result = detect_observed(*self._clouds, observed)
        except BaseException as error:  # handed to result()'s caller
            self._error = error
        self.seconds = time.perf_counter() - started

    @contextmanager
    def joined_on_error(self) -> Iterator[None]:
        """Around the localisation: if it fails, wait for a started detection before the
        error goes on (its own outcome is dropped), so no thread outlives the comparison."""
        try:
            yield
        except BaseException:
            if self._thread is not None:
                self._thread.join()
            raise

    def result(self) -> Detected | None:
        """Wait for the detection and return it; None if it was never started."""
        if self._thread is None:
            return None
        self._thread.join()
        if self._error is not None:
            raise self._error
        return self._result


def _detect_sample(
    detector: ChangeDetector,
    reference: tuple[NDArray[np.float64], NDArray[np.bool_] | None],
    scan: tuple[NDArray[np.float64], NDArray[np.bool_] | None],
    sample_points: int,
    random_state: int,
    compared: str,
) -> Detected:
    """:func:`detect_change` on at most ``sample_points`` of each cloud's chosen points (each
    cloud: its points, shape (n, 3), and which to score, None: all)."""
    rng = np.random.default_rng(random_state)
    sampled = False
    chosen = []
    for points, scored in (reference, scan):
        rows = np.arange(len(points)) if scored is None else np.flatnonzero(scored)
        if len(rows) > sample_points:
            rows = np.sort(rng.choice(rows, sample_points, replace=False))
            sampled = True
        chosen.append(np.asarray(points[rows], dtype=np.float64))  # float32 when read lean
    with threadpool_limits(limits=1, user_api="blas"):
        detection = detector.detect(chosen[0], chosen[1])
    if sampled:
        compared += f" (a random {sample_points:,} of each cloud at most)"
    return Detected(detection, compared)


def decide_change(
    detection: Detection,
    regions: Sequence[ChangedRegion],
    *,
    min_region_points: int,
    rule: str,
    method: str,
    variant: str,
    site_calibration: Mapping[str, Any] | None = None,
) -> Decision:
    """Apply the decision ``rule`` to the detector's score and the regions found.

    Parameters
    ----------
    detection : Detection
    regions : sequence of ChangedRegion
        The regions kept (local frame).
    min_region_points : int
        The size floor they passed.
    rule : {"regions", "detector", "either"}
    method, variant : str
        The detector's, to check a site calibration was learned for it.
    site_calibration : mapping, optional
        :func:`app.core.site_calibration.learn_site_calibration`'s result.

    Returns
    -------
    Decision
    """
    changed, tests, site = decide(
        DecisionInputs(
            rule=rule,
            method=method,
            variant=variant,
            score=float(detection.score),
            detector_threshold=float(detection.threshold),
            n_regions=len(regions),
            largest_region_extent_m=largest_extent(regions),
            min_region_points=min_region_points,
        ),
        site_calibration,
    )
    applied = bool(site["applied"])
    return Decision(
        changed=changed,
        rule=rule,
        detector_changed=bool(detection.changed),
        n_regions=len(regions),
        tests=tuple(DecisionTest.of(test) for test in tests),
        site=SiteProvenance(
            applied=applied,
            reason=None if applied else site["reason"],
            calibration=dict(site_calibration or {}),
        ),
    )
