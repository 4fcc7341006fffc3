"""What the service, the CLI and the core's reports read of a comparison's result.

:class:`Comparison` is the shape of :class:`~app.core.comparison.result.ComparisonResult`
that :mod:`app.jobs.results`, :mod:`app.jobs.execution`, :mod:`app.core.quality` and
:mod:`app.core.explanation` rely on (a test's stand-in pipeline provides the same), in place
of ``Any`` read with ``getattr``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from app.core.comparison.reports import (
    CalibrationReport,
    Explanation,
    QualityWarning,
    RegistrationReport,
    SensorOriginEntry,
    SideVisibility,
)


class Region(Protocol):
    """A changed (or uncertain) region in file coordinates."""

    @property
    def kind(self) -> str:
        """``"added"`` or ``"removed"``."""

    @property
    def n_points(self) -> int:
        """Points in it."""

    @property
    def centroid(self) -> Sequence[float]:
        """Its centre, 3 numbers."""

    @property
    def bbox_min(self) -> Sequence[float]:
        """Its lower corner, 3 numbers."""

    @property
    def bbox_max(self) -> Sequence[float]:
        """Its upper corner, 3 numbers."""

    @property
    def mean_distance(self) -> float:
        """Mean distance of its points to the other epoch's surface (metres)."""

    @property
    def max_distance(self) -> float:
        """Largest such distance (metres)."""

    @property
    def evidence(self) -> str:
        """``seen_empty``, ``surface_moved`` or ``no_coverage``."""

    @property
    def confidence(self) -> float | None:
        """Mean confidence of its points' labels, 0-1."""

    def to_json_dict(self) -> dict[str, Any]:
        """Plain JSON types."""


class Comparison(Protocol):
    """A comparison's result as its readers use it (see the module docstring)."""

    @property
    def score(self) -> float:
        """The detector's global score."""

    @property
    def threshold(self) -> float:
        """Its calibrated threshold."""

    @property
    def changed(self) -> bool:
        """The decision."""

    @property
    def params(self) -> Mapping[str, Any]:
        """Every parameter in effect."""

    @property
    def calibration(self) -> CalibrationReport:
        """The threshold's calibration, the decision's tests and the visibility report."""

    @property
    def registration(self) -> RegistrationReport:
        """The alignment's report (transform in file coordinates, fitness, ...)."""

    @property
    def regions(self) -> Sequence[Region]:
        """Changed regions, largest first."""

    @property
    def uncertain_regions(self) -> Sequence[Region]:
        """Regions the other epoch did not cover (never counted as change)."""

    @property
    def localisation(self) -> Mapping[str, Any]:
        """The localiser's parameters and estimates."""

    @property
    def sensor_origins(self) -> Mapping[str, list[SensorOriginEntry]]:
        """Per side, the origins used."""

    @property
    def visibility(self) -> Mapping[str, SideVisibility]:
        """Per side, where its origins came from and the visibility test it got."""

    @property
    def warnings(self) -> Sequence[str]:
        """The origins' own warnings."""

    @property
    def timings(self) -> Mapping[str, float]:
        """Seconds per stage."""

    @property
    def reference_label(self) -> NDArray[np.int8]:
        """Per reference point: 0 unchanged, 1 changed, -1 unobserved, shape (n,)."""

    @property
    def scan_label(self) -> NDArray[np.int8]:
        """Per scan point, shape (m,)."""

    @property
    def reference_distance(self) -> NDArray[np.float32]:
        """Per reference point: distance to the scan's surface, shape (n,)."""

    @property
    def scan_distance(self) -> NDArray[np.float32]:
        """Per scan point, shape (m,)."""

    @property
    def reference_region(self) -> NDArray[np.int32]:
        """Per reference point: index into ``regions``, -1 none, shape (n,)."""

    @property
    def scan_region(self) -> NDArray[np.int32]:
        """Per scan point, shape (m,)."""

    @property
    def quality_warnings(self) -> list[QualityWarning]:
        """:func:`app.core.quality.quality_warnings` of this result, computed once."""

    @property
    def explanation(self) -> Explanation:
        """:func:`app.core.explanation.explain_comparison` of this result, computed once."""

    def sensor_origins_json(self) -> dict[str, list[dict[str, Any]]]:
        """``sensor_origins`` as stored."""

    def visibility_json(self) -> dict[str, dict[str, Any]]:
        """``visibility`` as stored."""

    def write_labels_npz(self, path: str | Path) -> None:
        """Write the labels file."""
