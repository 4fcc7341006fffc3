"""Which sensor origin a comparison uses for one cloud, and why.

Order: the origin given as a parameter, then the file's (e.g. a PCD ``VIEWPOINT``), then an
estimate from the points (:func:`~app.core.origins.estimate.estimate_origin`) when it is
confident, else none (the localiser's coverage test).  A given or file origin is checked
against the data first: when the returns' elevations already fall on sharp rings from it, it is
kept without more work; otherwise the points are estimated, and the origin is contradicted when
the estimate is confident and lies more than :data:`CONTRADICTION_DISTANCE` away, or when the
origin lies outside the cloud's bounding box (a 360-degree lidar sits inside what it sees).  A
contradicted origin gives a warning and the estimate (or nothing) takes over.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.core.origins.estimate import OriginEstimate, estimate_origin
from app.core.origins.rings import ring_share

__all__ = ["CONTRADICTION_DISTANCE", "STATIONS_UNKNOWN", "ResolvedOrigin", "resolve_origin"]

CONTRADICTION_DISTANCE = 0.3
"""A given origin this far (metres) from a confident estimate is contradicted by the data."""
CONSISTENT_RING_SHARE = 0.85
"""From a right origin nearly every return of a lidar lies on a ring; so many is enough."""
BOUNDING_BOX_MARGIN = 0.5
CHECK_POINTS = 60_000
STATIONS_UNKNOWN = "stations_unknown"
"""Evidence entry (1.0) of a lidar cloud that no single origin explains and whose stations
were not recovered (:func:`~app.core.origins.station_recovery.resolve_stations`)."""


@dataclass(frozen=True)
class ResolvedOrigin:
    """The origin to use for one cloud (in the coordinates of the points given), its report.

    Attributes
    ----------
    origin : ndarray, shape (3,) or (k, 3) (several stations), or None
    source : {"given", "file", "estimated", "recovered"} or None
    confidence : float or None
        The estimate's confidence (None for a given or file origin kept unchecked-for-cause).
    warnings : list of str
    evidence : dict
        The estimate's evidence when one was made; the cloud's sampling and the stations
        searched when they were (:func:`~app.core.origins.station_recovery.resolve_stations`).
    station_confidence : list of float, optional
        Per station of a merged cloud whose stations were recovered: the share of points on
        its rings (:mod:`app.core.origins.station_recovery`).
    """

    origin: NDArray[np.float64] | None
    source: str | None
    confidence: float | None
    warnings: list[str] = field(default_factory=list)
    evidence: dict[str, float] = field(default_factory=dict)
    station_confidence: list[float] | None = None

    @property
    def stations_unknown(self) -> bool:
        """A lidar cloud merged from several stations that are not known nor recovered."""
        return self.origin is None and bool(self.evidence.get(STATIONS_UNKNOWN))

    def visibility_report(self) -> dict[str, Any]:
        """What was found out about the cloud's sensors: ``{"origins", "lidar_like", ...}``.

        ``origins``: "given", "file", "estimated", "recovered" or "none"; ``lidar_like`` (when
        the sampling was measured, with its figures), ``stations_recovered`` (when searched),
        ``stations_unknown``.
        """
        report: dict[str, Any] = {"origins": self.source or "none"}
        if "lidar_like" in self.evidence:
            report["lidar_like"] = bool(self.evidence["lidar_like"])
            report["lidar_twin_share"] = self.evidence.get("lidar_twin_share")
            report["lidar_spacing_spread"] = self.evidence.get("lidar_spacing_spread")
            if "lidar_noise_ratio" in self.evidence:
                report["lidar_noise_ratio"] = self.evidence["lidar_noise_ratio"]
        if "stations_recovered" in self.evidence:
            report["stations_recovered"] = int(self.evidence["stations_recovered"])
        report["stations_unknown"] = self.stations_unknown
        return report

    def report(self, to_file: Callable[[NDArray[np.float64]], NDArray[np.float64]]) -> list:
        """``[{"origin", "source", "confidence"}]``, one per station, mapped by ``to_file``."""
        if self.origin is None:
            return []
        origins = np.asarray(to_file(self.origin), dtype=np.float64).reshape(-1, 3)
        confidence = self.station_confidence or [self.confidence] * len(origins)
        return [
            {"origin": [float(value) for value in origin], "source": self.source, "confidence": c}
            for origin, c in zip(origins, confidence, strict=True)
        ]


def _consistent(points: NDArray[np.float64], origin: NDArray[np.float64]) -> bool:
    """Whether the returns' elevations from ``origin`` fall on sharp rings."""
    sample = points
    if len(points) > CHECK_POINTS:
        sample = points[np.random.default_rng(0).choice(len(points), CHECK_POINTS, replace=False)]
    horizontal = np.linalg.norm(sample[:, :2] - origin[:2], axis=1)
    usable = horizontal > 1.0
    if np.count_nonzero(usable) < 100:
        return False
    return ring_share(sample[usable, 2], horizontal[usable], float(origin[2])) >= (
        CONSISTENT_RING_SHARE
    )


def _outside(points: NDArray[np.float64], origin: NDArray[np.float64]) -> bool:
    low, high = points.min(axis=0), points.max(axis=0)
    return bool(
        np.any(origin < low - BOUNDING_BOX_MARGIN) or np.any(origin > high + BOUNDING_BOX_MARGIN)
    )


def resolve_origin(
    side: str,
    points: NDArray[np.float64],
    *,
    given: NDArray[np.float64] | None,
    from_file: NDArray[np.float64] | None,
    estimate: bool = True,
    random_state: int = 0,
    apex: bool = True,
) -> ResolvedOrigin:
    """Pick and check the origin of one cloud.

    Parameters
    ----------
    side : str
        "reference" or "scan" (for the warnings).
    points : ndarray, shape (n, 3)
        The cloud, in the frame the origin is used in (z up).
    given, from_file : ndarray, shape (3,), or None
        The parameter's and the file's origins, in the same frame as ``points``.
    estimate : bool
        Estimate from the points when no origin is given (or it is contradicted).
    random_state : int
        Seeds the estimate's subsamples (fixed by default, so a comparison replays exactly
        whatever its own seed).
    apex : bool
        Let the estimate search the rings' apex
        (:func:`~app.core.origins.estimate.estimate_origin`).

    Returns
    -------
    ResolvedOrigin
    """
    candidates = [("given", given), ("file", from_file)]
    source, origin = next(((s, o) for s, o in candidates if o is not None), (None, None))
    if origin is not None and _consistent(points, origin):
        return ResolvedOrigin(origin, source, None)
    found: OriginEstimate | None = None
    if estimate or origin is not None:
        found = estimate_origin(points, random_state=random_state, apex=apex)
    warnings: list[str] = []
    if origin is not None:
        described = f"the {side}'s {source} sensor origin {np.round(origin, 3).tolist()}"
        if found is not None and found.confident:
            gap = float(np.linalg.norm(found.origin - origin))
            if gap <= CONTRADICTION_DISTANCE:
                return ResolvedOrigin(origin, source, None, evidence=found.evidence)
            warnings.append(
                f"{described} is {gap:.2f} m from where the data say the sensor was "
                f"(confidence {found.confidence:.2f}); the estimate is used instead"
            )
        elif _outside(points, origin):
            warnings.append(
                f"{described} lies outside the cloud, where a 360-degree lidar cannot have "
                "stood; it is ignored (no origin could be estimated either)"
            )
            return ResolvedOrigin(None, None, None, warnings)
        else:
            return ResolvedOrigin(origin, source, None)
    if found is not None and found.confident:
        return ResolvedOrigin(
            found.origin, "estimated", round(found.confidence, 3), warnings, found.evidence
        )
    return ResolvedOrigin(None, None, None, warnings, found.evidence if found else {})
