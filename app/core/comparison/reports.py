"""The comparison's reports as frozen dataclasses, each with the JSON object it is stored as.

:class:`RegistrationReport` (the align stage's), :class:`SideVisibility` (what was found out
about one cloud's sensors and the visibility test it got); the decision is
:class:`~app.core.comparison.decide.Decision` and a quality warning
:class:`~app.core.quality.QualityWarning`.  The API mirrors them field by field
(``app.services.result_schemas``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.core.registration import Registration


@dataclass(frozen=True)
class RegistrationReport:
    """How the scan was aligned onto the reference.

    Attributes
    ----------
    transform : list of list of float
        4 x 4 matrix taking the scan file's coordinates to the reference file's.
    fitness : float
        Share of the scan's (downsampled) points near the reference once aligned.
    rmse : float or None
        Their RMS distance (metres); None when not finite.
    converged : bool
    iterations : int
    method : str
    max_correspondence_distance, voxel_size : float
        Metres.
    rotation_degrees : float
        The turn applied.
    enabled : bool
        False: compared without aligning (the fit is measured all the same).
    translation_m : float
        How far the alignment moved the scan's centre (metres).
    sample_points : int or None
        The points of each cloud it was estimated on, when a sample (a tiled comparison).
    """

    transform: list[list[float]]
    fitness: float
    rmse: float | None
    converged: bool
    iterations: int
    method: str
    max_correspondence_distance: float
    voxel_size: float
    rotation_degrees: float
    enabled: bool
    translation_m: float
    sample_points: int | None = None

    @classmethod
    def of(
        cls,
        registration: Registration,
        file_transform: NDArray[np.float64],
        *,
        enabled: bool,
        translation_m: float,
        sample_points: int | None = None,
    ) -> RegistrationReport:
        """The report of ``registration`` with its transform in file coordinates (4, 4)."""
        summary = registration.to_json_dict()
        summary["transform"] = file_transform.tolist()
        return cls(
            **summary, enabled=enabled, translation_m=translation_m, sample_points=sample_points
        )

    def to_json_dict(self) -> dict[str, Any]:
        """The stored object (a job's ``registration``)."""
        return {
            "transform": self.transform,
            "fitness": self.fitness,
            "rmse": self.rmse,
            "converged": self.converged,
            "iterations": self.iterations,
            "method": self.method,
            "max_correspondence_distance": self.max_correspondence_distance,
            "voxel_size": self.voxel_size,
            "rotation_degrees": self.rotation_degrees,
            "enabled": self.enabled,
            **({} if self.sample_points is None else {"sample_points": self.sample_points}),
            "translation_m": self.translation_m,
        }


@dataclass(frozen=True)
class SideVisibility:
    """What was found out about one cloud's sensors, and the test its candidates got.

    Attributes
    ----------
    origins : str
        given, file, estimated, recovered, trajectory or none.
    stations_unknown : bool
        A merged lidar cloud whose stations are neither known nor recovered.
    test : str or None
        The visibility test of the *other* cloud's view of its candidates (ray, trajectory,
        maps, surfaces, coverage, gaps).
    sampling : dict or None
        When the sampling was measured: ``lidar_like``, ``lidar_twin_share``,
        ``lidar_spacing_spread``.
    stations_recovered : int or None
        Stations found when they were searched.
    trajectory : dict or None
        A trajectory's summary (poses, groups, assignment...).
    """

    origins: str
    stations_unknown: bool
    test: str | None
    sampling: dict[str, Any] | None = None
    stations_recovered: int | None = None
    trajectory: dict[str, Any] | None = None

    @classmethod
    def of(cls, report: Mapping[str, Any], test: str | None) -> SideVisibility:
        """From an origin's ``visibility_report()`` and the test the localiser chose."""
        sampling_keys = ("lidar_like", "lidar_twin_share", "lidar_spacing_spread")
        return cls(
            origins=report["origins"],
            stations_unknown=report["stations_unknown"],
            test=test,
            sampling={key: report[key] for key in sampling_keys if key in report}
            if "lidar_like" in report
            else None,
            stations_recovered=report.get("stations_recovered"),
            trajectory=report.get("trajectory"),
        )

    def to_json_dict(self) -> dict[str, Any]:
        """The stored object (``visibility[side]``, also in ``calibration["visibility"]``)."""
        report: dict[str, Any] = {"origins": self.origins, **(self.sampling or {})}
        if self.stations_recovered is not None:
            report["stations_recovered"] = self.stations_recovered
        report["stations_unknown"] = self.stations_unknown
        if self.trajectory is not None:
            report["trajectory"] = self.trajectory
        report["test"] = self.test
        return report
