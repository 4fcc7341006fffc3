"""One comparison as explicit stages, each taking and returning dataclasses.

:func:`app.core.pipeline.compare` runs them in order; each can also be called on its own (to
align a subsample, localise a crop of both clouds, or decide on scores computed elsewhere):

1. :mod:`~app.core.comparison.load`: :func:`load_pair` -> :class:`LoadedPair`;
2. :mod:`~app.core.comparison.origins`: :func:`resolve_reference_origins`,
   :func:`resolve_scan_origins` -> :class:`CloudOrigins` (both: :class:`SensorOrigins`);
3. :mod:`~app.core.comparison.align`: :func:`align_scan` -> :class:`Alignment`;
4. :mod:`~app.core.comparison.localise`: :func:`localise_pair` ->
   :class:`~app.core.localise.Localisation`;
5. :mod:`~app.core.comparison.decide`: :func:`detect_change` -> :class:`Detected`, then
   :func:`decide_change` -> :class:`Decision`;
6. :mod:`~app.core.comparison.assemble`: :func:`assemble_result` ->
   :class:`ComparisonResult` (:mod:`~app.core.comparison.result`).

:mod:`~app.core.comparison.memory` holds what a geometry cache keeps of the reference;
:mod:`~app.core.comparison.reports` the typed reports (:class:`RegistrationReport`,
:class:`SideVisibility`) with the JSON each is stored as; :mod:`~app.core.comparison.protocol`
the :class:`Comparison` protocol that the service and the reports read a result through.
This module lists the package's public names (imported on first use).
"""

from importlib import import_module
from typing import Any

_HOMES = {
    "Alignment": "align",
    "align_scan": "align",
    "assemble_result": "assemble",
    "Detected": "decide",
    "decide_change": "decide",
    "detect_change": "decide",
    "LoadedPair": "load",
    "load_pair": "load",
    "PairOptions": "load",
    "localise_pair": "localise",
    "ReferenceMemory": "memory",
    "CloudOrigins": "origins",
    "SensorOrigins": "origins",
    "resolve_reference_origins": "origins",
    "resolve_scan_origins": "origins",
    "Comparison": "protocol",
    "CalibrationReport": "reports",
    "Decision": "reports",
    "DecisionTest": "reports",
    "LidarSampling": "reports",
    "RegistrationReport": "reports",
    "SensorOriginEntry": "reports",
    "SideVisibility": "reports",
    "SiteProvenance": "reports",
    "ComparisonResult": "result",
    "RegionSummary": "result",
}
"""Where each public name lives: imported on first use, so that reading a result's types
(:mod:`~app.core.comparison.result`, :mod:`~app.core.comparison.reports`) does not load the
stages' libraries (registration, the localiser)."""

__all__ = sorted(_HOMES)


def __getattr__(name: str) -> Any:
    """The public name ``name`` from its module (see :data:`_HOMES`)."""
    if name not in _HOMES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(import_module(f"{__name__}.{_HOMES[name]}"), name)
