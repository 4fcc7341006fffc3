"""The typed parts of a :class:`~app.core.comparison.result.ComparisonResult` that tests build
by hand (a stand-in pipeline's, a finished job's): each from the few fields a test cares about,
the others plausible defaults."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from app.core.comparison.reports import (
    CalibrationReport,
    Decision,
    DecisionTest,
    RegistrationReport,
    SensorOriginEntry,
    SiteProvenance,
)


def registration_report(**fields: Any) -> RegistrationReport:
    """An identity alignment's report, with ``fields`` replaced."""
    defaults: dict[str, Any] = {
        "transform": np.eye(4).tolist(),
        "fitness": 1.0,
        "rmse": 0.01,
        "converged": True,
        "iterations": 1,
        "method": "small_gicp",
        "max_correspondence_distance": 0.3,
        "voxel_size": 0.1,
        "rotation_degrees": 0.0,
        "enabled": True,
        "translation_m": 0.0,
    }
    return RegistrationReport(**{**defaults, **fields})


def calibration_report(
    detector: Mapping[str, Any] | None = None,
    *,
    changed: bool = True,
    rule: str = "regions",
    detector_changed: bool = False,
    n_regions: int = 0,
    tests: Sequence[DecisionTest] = (),
) -> CalibrationReport:
    """A calibration with the detector's figures ``detector`` and a decision by ``rule``,
    no site calibration and no visibility report."""
    site = SiteProvenance(applied=False, reason="no site calibration")
    return CalibrationReport(
        detector=dict(detector or {}),
        compared_points="all",
        site=site,
        visibility={},
        decision=Decision(changed, rule, detector_changed, n_regions, tuple(tests), site),
    )


def sensor_origin_entries(
    origins: Mapping[str, Sequence[Mapping[str, Any]]],
) -> dict[str, list[SensorOriginEntry]]:
    """Per side, entries as stored (``{"origin", "source", "confidence"}`` or a trajectory's
    report), typed."""
    return {
        side: [SensorOriginEntry.of(entry) for entry in entries]
        for side, entries in origins.items()
    }
