"""EMD change detectors of Amorim, Rocha & Dias: PCA, GMM and plane extraction.

Each method comes as ``variant="paper"`` (the paper as written, for reproduction) and
``variant="improved"`` (the default: the paper's instabilities fixed, see docs/detectors.md).

>>> detector = make_detector("gmm", random_state=0)
>>> detection = detector.detect(reference_points, scan_points)  # doctest: +SKIP
>>> detection.changed, detection.score, detection.threshold  # doctest: +SKIP
"""

from __future__ import annotations

from typing import Any

from app.core.detectors.base import VARIANTS, ChangeDetector, Detection
from app.core.detectors.gmm import GmmDetector
from app.core.detectors.pca import PcaDetector
from app.core.detectors.planes import PlanesDetector
from app.core.errors import InputError

METHODS = ("gmm", "pca", "planes")

_DETECTORS: dict[str, type[ChangeDetector]] = {
    "gmm": GmmDetector,
    "pca": PcaDetector,
    "planes": PlanesDetector,
}


def make_detector(
    method: str, variant: str = "improved", *, random_state: int = 0, **params: Any
) -> ChangeDetector:
    """Build a detector by name.

    Parameters
    ----------
    method : {"gmm", "pca", "planes"}
    variant : {"improved", "paper"}
    random_state : int
        Seeds every random choice; same inputs and seed give the same result.
    **params
        Hyper-parameters of that method and variant (``detector.get_params()`` lists them);
        ``make_detector(method, **detector.get_params())`` rebuilds an identical detector.

    Raises
    ------
    InputError
        Unknown method, variant or parameter, or an invalid value; the message names the
        valid ones.
    """
    if method not in _DETECTORS:
        raise InputError(f"unknown detector method {method!r}; valid: {list(METHODS)}")
    if variant not in VARIANTS:
        raise InputError(f"unknown detector variant {variant!r}; valid: {list(VARIANTS)}")
    return _DETECTORS[method](variant, random_state=random_state, **params)


__all__ = [
    "METHODS",
    "VARIANTS",
    "ChangeDetector",
    "Detection",
    "GmmDetector",
    "PcaDetector",
    "PlanesDetector",
    "make_detector",
]
