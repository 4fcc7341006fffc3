"""How well labels match a synthetic pair's ground truth (benchmarks and tests).

:func:`changed_iou` scores the per-point labels of a comparison (or of
:func:`app.core.localise.localise_changes`) against the changed and observed masks that the
synthetic scene generators (:mod:`app.core.datasets.scenes`, :mod:`app.core.datasets.lidar`) return
with their pairs.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from app.core.labels import LABEL_CHANGED

__all__ = ["changed_iou"]


def changed_iou(pair: Any, labelled: Any) -> float:
    """IoU of changed points of both clouds over the points the ground truth marks observed.

    Parameters
    ----------
    pair : SyntheticPair or LidarPair
        Has ``reference_changed``/``scan_changed`` and ``reference_observed``/``scan_observed``
        masks, shapes (n,) and (m,).
    labelled : Localisation or ComparisonResult
        Has ``reference_label``/``scan_label``, shapes (n,) and (m,).

    Returns
    -------
    float
        1.0 when neither the labels nor the truth mark any observed point changed.
    """
    intersection = union = 0
    for label, changed, observed in (
        (labelled.reference_label, pair.reference_changed, pair.reference_observed),
        (labelled.scan_label, pair.scan_changed, pair.scan_observed),
    ):
        predicted = label == LABEL_CHANGED
        intersection += np.count_nonzero(predicted & changed & observed)
        union += np.count_nonzero((predicted | changed) & observed)
    return intersection / union if union else 1.0
