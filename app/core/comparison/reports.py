"""The comparison's reports as frozen dataclasses, each with the JSON object it is stored as
(``to_json_dict()``).

:class:`RegistrationReport` (the align stage's); :class:`Decision` with its
:class:`DecisionTest` list and :class:`SiteProvenance` (the decide stage's);
:class:`SideVisibility` with its :class:`LidarSampling` (what was found out about one cloud's
sensors and the visibility test it got); :class:`SensorOriginEntry` (one origin used);
:class:`CalibrationReport` (the threshold's calibration with the decision and visibility);
:class:`QualityWarning` (one of :func:`app.core.quality.quality_warnings`) and
:class:`Explanation` with its :class:`LargestRegion`
(:func:`app.core.explanation.explain_decision`).  The API mirrors them field by field
(``app.services.result_schemas``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
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
class LidarSampling:
    """Whether a cloud's sampling was measured to be a lidar's, with its figures
    (:func:`app.core.origins.sampling.lidar_sampling`).

    Attributes
    ----------
    lidar_like : bool
    lidar_twin_share : float or None
        Share of points with a twin at the lidar's angular step.
    lidar_spacing_spread : float or None
        Spread of the spacing along the rings.
    lidar_noise_ratio : float or None
        The points' noise against their spacing (the twin share needed falls as it grows).
    """

    lidar_like: bool
    lidar_twin_share: float | None
    lidar_spacing_spread: float | None
    lidar_noise_ratio: float | None = None

    def to_json_dict(self) -> dict[str, Any]:
        """The figures, as stored in ``visibility[side]`` (the noise ratio when measured)."""
        report: dict[str, Any] = {
            "lidar_like": self.lidar_like,
            "lidar_twin_share": self.lidar_twin_share,
            "lidar_spacing_spread": self.lidar_spacing_spread,
        }
        if self.lidar_noise_ratio is not None:
            report["lidar_noise_ratio"] = self.lidar_noise_ratio
        return report


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
    sampling : LidarSampling or None
        When the sampling was measured.
    stations_recovered : int or None
        Stations found when they were searched.
    trajectory : mapping or None
        A trajectory's summary (poses, groups, assignment...: the trajectory's own report,
        ``app.core.origins.trajectory_origin``).
    """

    origins: str
    stations_unknown: bool
    test: str | None
    sampling: LidarSampling | None = None
    stations_recovered: int | None = None
    trajectory: Mapping[str, Any] | None = None

    @classmethod
    def of(cls, report: Mapping[str, Any], test: str | None) -> SideVisibility:
        """From an origin's ``visibility_report()`` and the test the localiser chose."""
        return cls(
            origins=report["origins"],
            stations_unknown=report["stations_unknown"],
            test=test,
            sampling=LidarSampling(
                report["lidar_like"],
                report.get("lidar_twin_share"),
                report.get("lidar_spacing_spread"),
                report.get("lidar_noise_ratio"),
            )
            if "lidar_like" in report
            else None,
            stations_recovered=report.get("stations_recovered"),
            trajectory=report.get("trajectory"),
        )

    def to_json_dict(self) -> dict[str, Any]:
        """The stored object (``visibility[side]``, also in ``calibration["visibility"]``)."""
        report: dict[str, Any] = {"origins": self.origins}
        if self.sampling is not None:
            report.update(self.sampling.to_json_dict())
        if self.stations_recovered is not None:
            report["stations_recovered"] = self.stations_recovered
        report["stations_unknown"] = self.stations_unknown
        if self.trajectory is not None:
            report["trajectory"] = dict(self.trajectory)
        report["test"] = self.test
        return report


@dataclass(frozen=True)
class SensorOriginEntry:
    """One sensor origin a comparison used, in that cloud's file frame.

    Attributes
    ----------
    source : str
        given, file, estimated, recovered or trajectory.
    origin : list of float or None
        [x, y, z] (None for a trajectory).
    confidence : float or None
        0-1 (None for a trajectory).
    trajectory : mapping or None
        A trajectory's report instead (``source``, poses, time span, groups, path...).
    """

    source: str
    origin: list[float] | None = None
    confidence: float | None = None
    trajectory: Mapping[str, Any] | None = None

    @classmethod
    def of(cls, entry: Mapping[str, Any]) -> SensorOriginEntry:
        """From one entry of :meth:`app.core.origins.resolve.ResolvedOrigin.report`."""
        if "origin" not in entry:  # a trajectory's report
            return cls(source=str(entry["source"]), trajectory=dict(entry))
        return cls(source=entry["source"], origin=entry["origin"], confidence=entry["confidence"])

    def to_json_dict(self) -> dict[str, Any]:
        """The stored object (one entry of ``sensor_origins[side]``)."""
        if self.trajectory is not None:
            return {**self.trajectory, "source": self.source}
        return {"origin": self.origin, "source": self.source, "confidence": self.confidence}


@dataclass(frozen=True)
class DecisionTest:
    """One test of the decision rule (:func:`app.core.site_calibration.decide`).

    Attributes
    ----------
    statistic : {"largest_region_extent_m", "score"}
    value, threshold : float
    comparison : str
        ``">"``: the test fires when the value is above the threshold.
    source : {"default", "site"}
        Where the threshold came from (site: learned from the site's reviewed jobs).
    fires : bool
    n_regions, min_region_points : int or None
        The region test's counts (None for the score test).
    """

    statistic: str
    value: float
    comparison: str
    threshold: float
    source: str
    fires: bool
    n_regions: int | None = None
    min_region_points: int | None = None

    @classmethod
    def of(cls, test: Mapping[str, Any]) -> DecisionTest:
        """From one test as :func:`app.core.site_calibration.decide` returns it."""
        return cls(
            statistic=test["statistic"],
            value=test["value"],
            comparison=test["comparison"],
            threshold=test["threshold"],
            source=test["source"],
            fires=test["fires"],
            n_regions=test.get("n_regions"),
            min_region_points=test.get("min_region_points"),
        )

    def to_json_dict(self) -> dict[str, Any]:
        """The stored object (one of ``calibration["decision"]["tests"]``)."""
        test: dict[str, Any] = {
            "statistic": self.statistic,
            "value": self.value,
            "comparison": self.comparison,
            "threshold": self.threshold,
            "source": self.source,
        }
        if self.n_regions is not None:
            test["n_regions"] = self.n_regions
        if self.min_region_points is not None:
            test["min_region_points"] = self.min_region_points
        test["fires"] = self.fires
        return test


@dataclass(frozen=True)
class SiteProvenance:
    """Whether a site's learned thresholds applied to a comparison.

    Attributes
    ----------
    applied : bool
    reason : str or None
        Why not, when not applied.
    calibration : mapping
        The site's calibration as given (:func:`app.core.site_calibration.learn_site_calibration`:
        status, method, variant, thresholds...; empty without one).
    """

    applied: bool
    reason: str | None = None
    calibration: Mapping[str, Any] = field(default_factory=dict)

    def to_json_dict(self) -> dict[str, Any]:
        """The stored object (``calibration["site"]``): the site's calibration with
        ``applied`` (and ``reason``) set."""
        provenance = dict(self.calibration)
        provenance["applied"] = self.applied
        if self.reason is not None:
            provenance["reason"] = self.reason
        return provenance


@dataclass(frozen=True)
class Decision:
    """The comparison's verdict and the tests that made it.

    Attributes
    ----------
    changed : bool
    rule : {"regions", "detector", "either"}
    detector_changed : bool
        The detector's own verdict (score above its threshold).
    n_regions : int
    tests : tuple of DecisionTest
        The decisive tests (:func:`app.core.site_calibration.decide`).
    site : SiteProvenance
    """

    changed: bool
    rule: str
    detector_changed: bool
    n_regions: int
    tests: tuple[DecisionTest, ...]
    site: SiteProvenance

    def report(self) -> dict[str, Any]:
        """``calibration["decision"]``: rule, the detector's verdict, regions and tests."""
        return {
            "rule": self.rule,
            "detector_changed": self.detector_changed,
            "n_regions": self.n_regions,
            "tests": [test.to_json_dict() for test in self.tests],
        }


@dataclass(frozen=True)
class CalibrationReport:
    """How the threshold was calibrated, the decision and what was found out about each
    cloud's sensors (a result's ``calibration``).

    Attributes
    ----------
    detector : mapping
        The detector's own calibration figures (:attr:`app.core.detectors.base.Detection.
        calibration`: resamples, false alarm rate, working points...; they vary by detector).
    compared_points : str
        ``"mutually observed"`` or ``"all"`` (with the sample size when a sample).
    site : SiteProvenance
    visibility : mapping of str to SideVisibility
        Per side (reference, scan).
    decision : Decision
    """

    detector: Mapping[str, Any]
    compared_points: str
    site: SiteProvenance
    visibility: Mapping[str, SideVisibility]
    decision: Decision

    def to_json_dict(self) -> dict[str, Any]:
        """The stored object: the detector's figures, then ``compared_points``, ``site``,
        ``visibility`` and ``decision``."""
        report = dict(self.detector)
        report["compared_points"] = self.compared_points
        report["site"] = self.site.to_json_dict()
        report["visibility"] = {side: seen.to_json_dict() for side, seen in self.visibility.items()}
        report["decision"] = self.decision.report()
        return report


FIX_ACTIONS = {
    "check_pairing": "check that both scans are of the same place, or skip the alignment",
    "check_alignment": "check that the alignment found the right match, or skip the alignment",
    "widen_coverage": "rescan so that both scans cover the same part of the place",
    "give_sensor_origin": "give the sensor position of the side named in the detail",
    "check_sensor_origin": "check the sensor position given",
    "check_trajectory": "check that the trajectory covers the whole recording, on its clock",
}
"""What each ``how_to_fix["action"]`` asks, without naming any interface's knob."""


@dataclass(frozen=True)
class QualityWarning:
    """One quality warning (:mod:`app.core.quality` says which there are), stored as
    :meth:`to_json_dict`.

    Attributes
    ----------
    code : str
    message : str
        One sentence, with units.
    explanation : str
        What it means for the result.
    action : str
        One of :data:`FIX_ACTIONS`.
    value, limit : float, optional
        The measured value and the limit it crossed.
    unit : str, optional
    side : {"reference", "scan"}, optional
    """

    code: str
    message: str
    explanation: str
    action: str
    value: float | None = None
    limit: float | None = None
    unit: str | None = None
    side: str | None = None

    def to_json_dict(self) -> dict[str, Any]:
        """``{"code", "message", value..., "detail", "how_to_fix"}`` (measured fields only)."""
        measured = {
            key: value
            for key, value in (
                ("value", self.value),
                ("limit", self.limit),
                ("unit", self.unit),
                ("side", self.side),
            )
            if value is not None
        }
        return {
            "code": self.code,
            "message": self.message,
            **measured,
            "detail": {**measured, "explanation": self.explanation},
            "how_to_fix": {"action": self.action, "summary": FIX_ACTIONS[self.action]},
        }


@dataclass(frozen=True)
class LargestRegion:
    """The region with the most points, as the explanation names it.

    Attributes
    ----------
    index : int
        Its index in the result's regions.
    kind : {"added", "removed"}
    n_points : int
    size_m : tuple of float, shape (3,)
        Its bounding box's extents, metres (rounded to millimetres).
    """

    index: int
    kind: str
    n_points: int
    size_m: tuple[float, ...]

    def to_json_dict(self) -> dict[str, Any]:
        """``{"index", "kind", "n_points", "size_m"}`` (``size_m`` a list of 3 numbers)."""
        return {
            "index": self.index,
            "kind": self.kind,
            "n_points": self.n_points,
            "size_m": list(self.size_m),
        }


@dataclass(frozen=True)
class Explanation:
    """Why a comparison decided what it did (:func:`explain_decision` says how each field is
    found), and its one line of ``text``.

    Attributes
    ----------
    decision : {"changed", "unchanged"}
    rule : {"regions", "detector", "either"}
    decided_by : str
        "regions", "detector" or, under ``"either"``, which of them said changed.
    n_regions, n_region_points : int
    min_region_points, dropped_clusters : int or None
    largest_region : LargestRegion or None
        None without regions.
    score, threshold : float or None
    detector_changed : bool or None
    agrees : bool
        Whether the regions and the detector say the same.
    site_test : dict or None
        The decision test that used the site's learned threshold, when one did.
    text : str
    """

    decision: str
    rule: str
    decided_by: str
    n_regions: int
    n_region_points: int
    min_region_points: int | None
    dropped_clusters: int | None
    largest_region: LargestRegion | None
    score: float | None
    threshold: float | None
    detector_changed: bool | None
    agrees: bool
    site_test: dict[str, Any] | None
    text: str

    def to_json_dict(self) -> dict[str, Any]:
        """The explanation as stored and shown by the API, in this key order."""
        largest = self.largest_region
        return {
            "decision": self.decision,
            "rule": self.rule,
            "decided_by": self.decided_by,
            "n_regions": self.n_regions,
            "n_region_points": self.n_region_points,
            "min_region_points": self.min_region_points,
            "dropped_clusters": self.dropped_clusters,
            "largest_region": None if largest is None else largest.to_json_dict(),
            "score": self.score,
            "threshold": self.threshold,
            "detector_changed": self.detector_changed,
            "agrees": self.agrees,
            "site_test": None if self.site_test is None else dict(self.site_test),
            "text": self.text,
        }
