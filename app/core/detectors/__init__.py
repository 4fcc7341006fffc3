"""EMD change detectors of Amorim, Rocha & Dias: PCA, GMM and plane extraction.

Each method comes as ``variant="paper"`` (the paper as written, for reproduction) and
``variant="improved"`` (the default: the paper's instabilities fixed, see docs/detectors.md).

>>> detector = make_detector("gmm", random_state=0)
>>> detection = detector.detect(reference_points, scan_points)  # doctest: +SKIP
>>> detection.changed, detection.score, detection.threshold  # doctest: +SKIP
"""

from __future__ import annotations

import importlib
import sys
import threading
from typing import Any

from app.core.detectors.base import VARIANTS, ChangeDetector, Detection
from app.core.detectors.gmm import GmmDetector
from app.core.detectors.pca import PcaDetector
from app.core.detectors.planes import PlanesDetector
from app.core.errors import InputError

METHODS = ("gmm", "pca", "planes")

METHOD_ALIASES: dict[str, str] = {
    "gmm-emd": "gmm",
    "pca-emd": "pca",
    "pe": "planes",
    "pe-emd": "planes",
    "planes-emd": "planes",
}
"""The paper's names (GMM-EMD, PCA-EMD, PE-EMD for plane extraction) and their canonical method;
matched case-insensitively, like the canonical names, by :func:`canonical_method`."""

LIBRARIES = ("scipy.optimize", "scipy.sparse.csgraph")
"""What the detectors import on first use: scipy.optimize (the EMD's linear programme, ~0.06 CPU
s). Their k-means, t quantile and EMD need neither scikit-learn, scipy.stats nor POT (~0.9 CPU
s of imports): :mod:`app.core.detectors.kmeans`, ``scipy.special.stdtrit``, ``scipy.optimize``.
And scipy.sparse.csgraph, which the localiser's region clustering imports on first use
(:func:`app.core.localise.regions.cluster_labels`, ~0.08 CPU s): loaded here beside the
neighbour searches rather than in the clustering, where the other side's thread waits for it,
or in the command's serial start-up (``app.core.tiling.merge`` imports it on first use)."""


def warm_up() -> threading.Thread | None:
    """Import :data:`LIBRARIES` on a thread of their own, while the caller does other work (a
    comparison aligns and localises first, mostly in numpy and KD-tree code that releases the
    GIL); the detectors' own imports then find them loaded, or wait for them.

    Returns
    -------
    threading.Thread or None
        The thread (a daemon), or None when they are loaded already or no thread can start.
    """
    missing = [name for name in LIBRARIES if name not in sys.modules]
    if not missing:
        return None

    def load() -> None:
        for name in missing:
            try:
                importlib.import_module(name)
            except Exception:  # the detector's own import reports it
                return

    thread = threading.Thread(target=load, name="detector-imports", daemon=True)
    try:
        thread.start()
    except RuntimeError:  # no thread to be had (an address-space cap): imported when used
        return None
    return thread


_DETECTORS: dict[str, type[ChangeDetector]] = {
    "gmm": GmmDetector,
    "pca": PcaDetector,
    "planes": PlanesDetector,
}


def canonical_method(method: str) -> str:
    """The canonical name of a detector method, given it or one of the paper's names.

    ``"PE-EMD"``, ``"pe"`` and ``"planes"`` all give ``"planes"`` (case-insensitive, surrounding
    spaces ignored); the canonical name is what results and stored settings carry.

    Raises
    ------
    InputError
        Not a method or alias; the message lists the valid names.
    """
    if not isinstance(method, str):
        raise InputError(f"detector method must be a string, got {method!r}")
    name = method.strip().lower()
    name = METHOD_ALIASES.get(name, name)
    if name not in _DETECTORS:
        raise InputError(
            f"unknown detector method {method!r}; valid: {list(METHODS)} "
            f"(or the paper's names: {', '.join(sorted(METHOD_ALIASES))})"
        )
    return name


def make_detector(
    method: str, variant: str = "improved", *, random_state: int = 0, **params: Any
) -> ChangeDetector:
    """Build a detector by name.

    Parameters
    ----------
    method : {"gmm", "pca", "planes"}
        Or one of the paper's names (:data:`METHOD_ALIASES`, e.g. ``"PE-EMD"``).
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
    method = canonical_method(method)
    if variant not in VARIANTS:
        raise InputError(f"unknown detector variant {variant!r}; valid: {list(VARIANTS)}")
    return _DETECTORS[method](variant, random_state=random_state, **params)


__all__ = [
    "LIBRARIES",
    "METHODS",
    "METHOD_ALIASES",
    "VARIANTS",
    "ChangeDetector",
    "Detection",
    "GmmDetector",
    "PcaDetector",
    "PlanesDetector",
    "canonical_method",
    "make_detector",
    "warm_up",
]
