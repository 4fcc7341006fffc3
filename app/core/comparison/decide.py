"""Stage 5, **decide**: the paper's global score between the parts of both clouds that both
sensors observed, then the decision rule (:mod:`app.core.site_calibration`).

Points the other scan could not see are not evidence of change, so the detector compares the
mutually observed points (all of them when fewer than :data:`app.core.cloud.MIN_POINTS` are);
its threshold is calibrated from the clouds' own resampling noise
(:mod:`app.core.detectors`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import threadpool_limits

from app.core.cloud import MIN_POINTS
from app.core.comparison.reports import Decision, DecisionTest, SiteProvenance
from app.core.detectors.base import ChangeDetector, Detection
from app.core.labels import LABEL_UNOBSERVED
from app.core.localise import ChangedRegion
from app.core.site_calibration import DecisionInputs, decide, largest_extent
from app.core.threads import available_threads, concurrently


class PointLabels(Protocol):
    """Both clouds' labels (a :class:`~app.core.localise.Localisation` has them)."""

    @property
    def reference_label(self) -> NDArray[np.int8]:
        """Shape (n,)."""

    @property
    def scan_label(self) -> NDArray[np.int8]:
        """Shape (m,)."""


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
    localisation: PointLabels,
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
    reference_observed = localisation.reference_label != LABEL_UNOBSERVED
    scan_observed = localisation.scan_label != LABEL_UNOBSERVED
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
            # np.compress: the rows a boolean index takes, in their order, in half its time;
            # one cloud on a helper thread (the gathers release the GIL): the comparison's
            # serial end, 40 -> ~10 ms at 1M + 1M
            detection = detector.detect(
                *concurrently(
                    available_threads(),
                    lambda: np.compress(reference_observed, reference_points, axis=0),
                    lambda: np.compress(scan_observed, aligned_scan, axis=0),
                )
            )
        else:
            detection = detector.detect(reference_points, aligned_scan)
    return Detected(detection, compared)


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
