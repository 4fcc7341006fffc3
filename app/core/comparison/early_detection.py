"""Stage 5's detector started while stage 4 still clusters its regions.

The detector scores the points both sensors observed (:func:`~app.core.comparison.decide.
detect_change`), and which points are unobserved is final once the localiser's visibility test
has run: its regions step after that only turns changed points of too small clusters into
unchanged ones, both observed.  On two threads the detection (~0.5 CPU s at 1M + 1M, most of
it on one thread) then runs beside the regions' clustering instead of after it: the
comparison's serial end is shorter, the result the same.

:class:`EarlyDetection` checks that: it keeps the labels it started from and hands its result
over only when the final labels observe exactly the same points; otherwise (or after an
error) the pipeline detects again from the final labels, as without it.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from app.core.comparison.decide import Detected, detect_change
from app.core.detectors.base import ChangeDetector
from app.core.labels import LABEL_UNOBSERVED
from app.core.localise import Localisation

__all__ = ["EarlyDetection", "LabelsSnapshot"]


@dataclass(frozen=True)
class LabelsSnapshot:
    """Both clouds' labels as they were when the detection started.

    Attributes
    ----------
    reference_label : ndarray, shape (n,), int8
    scan_label : ndarray, shape (m,), int8
    """

    reference_label: NDArray[np.int8]
    scan_label: NDArray[np.int8]

    def observes_as(self, localisation: Localisation) -> bool:
        """Whether ``localisation``'s labels leave exactly these points unobserved."""
        return all(
            np.array_equal(started == LABEL_UNOBSERVED, final == LABEL_UNOBSERVED)
            for started, final in (
                (self.reference_label, localisation.reference_label),
                (self.scan_label, localisation.scan_label),
            )
        )


class EarlyDetection:
    """:func:`~app.core.comparison.decide.detect_change` on a thread of its own, started from
    the localiser's ``on_labelled`` hook (:meth:`start`) and taken after stage 4 (:meth:`take`).

    Parameters
    ----------
    detector : ChangeDetector
    reference_points : ndarray, shape (n, 3), float64
        The reference as the localiser gets it.
    """

    def __init__(self, detector: ChangeDetector, reference_points: NDArray[np.float64]):
        self._detector = detector
        self._reference_points = reference_points
        self._thread: threading.Thread | None = None
        self._labels: LabelsSnapshot | None = None
        self._detected: Detected | None = None
        self.seconds = 0.0
        """Wall seconds of the detection on its thread (0 before it ran)."""

    def start_for(
        self, aligned_scan: NDArray[np.float64]
    ) -> Callable[[NDArray[np.int8], NDArray[np.int8]], None]:
        """The ``on_labelled`` hook of a localisation of ``aligned_scan`` (shape (m, 3))."""

        def start(reference_label: NDArray[np.int8], scan_label: NDArray[np.int8]) -> None:
            self._labels = LabelsSnapshot(reference_label.copy(), scan_label.copy())
            self._thread = threading.Thread(
                target=self._run, args=(aligned_scan,), name="early-detection", daemon=True
            )
            try:
                self._thread.start()
            except RuntimeError:  # no thread to be had: the pipeline detects afterwards
                self._thread = None

        return start

    def _run(self, aligned_scan: NDArray[np.float64]) -> None:
        started = time.perf_counter()
        try:
            self._detected = detect_change(
                self._detector, self._reference_points, aligned_scan, self._labels
            )
        except Exception:  # raised again by the pipeline's own detection
            self._detected = None
        self.seconds = time.perf_counter() - started

    def wait(self) -> None:
        """Wait for the detection, if it started (also when stage 4 failed after its start:
        no thread outlives the comparison)."""
        if self._thread is not None:
            self._thread.join()

    def take(self, localisation: Localisation) -> Detected | None:
        """Wait for the detection; its result when it ran on the points ``localisation``
        observes, else None (not started, failed, or other labels: detect again)."""
        if self._thread is None or self._labels is None:
            return None
        self.wait()
        detected, self._detected = self._detected, None
        if detected is None or not self._labels.observes_as(localisation):
            return None
        return detected
