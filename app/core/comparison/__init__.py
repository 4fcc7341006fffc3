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
This module lists the package's public names.
"""

from app.core.comparison.align import Alignment, align_scan
from app.core.comparison.assemble import assemble_result
from app.core.comparison.decide import Decision, Detected, decide_change, detect_change
from app.core.comparison.load import LoadedPair, load_pair
from app.core.comparison.localise import localise_pair
from app.core.comparison.memory import ReferenceMemory
from app.core.comparison.origins import (
    CloudOrigins,
    SensorOrigins,
    resolve_reference_origins,
    resolve_scan_origins,
)
from app.core.comparison.protocol import Comparison
from app.core.comparison.reports import RegistrationReport, SideVisibility
from app.core.comparison.result import ComparisonResult, RegionSummary

__all__ = [
    "Alignment",
    "CloudOrigins",
    "Comparison",
    "ComparisonResult",
    "Decision",
    "Detected",
    "LoadedPair",
    "ReferenceMemory",
    "RegionSummary",
    "RegistrationReport",
    "SensorOrigins",
    "SideVisibility",
    "align_scan",
    "assemble_result",
    "decide_change",
    "detect_change",
    "load_pair",
    "localise_pair",
    "resolve_reference_origins",
    "resolve_scan_origins",
]
