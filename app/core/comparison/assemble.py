"""Stage 6, **assemble**: every stage's output as one :class:`ComparisonResult`, in the files'
coordinates and the source files' row order."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.core.cloud import PointCloud
from app.core.comparison.align import Alignment
from app.core.comparison.decide import Detected
from app.core.comparison.load import LoadedPair
from app.core.comparison.origins import SensorOrigins
from app.core.comparison.reports import (
    CalibrationReport,
    Decision,
    SensorOriginEntry,
    SideVisibility,
)
from app.core.comparison.result import ComparisonResult, region_summary
from app.core.labels import LABEL_UNOBSERVED
from app.core.localise import Localisation
from app.core.registration import apply_transform


def assemble_result(
    loaded: LoadedPair,
    origins: SensorOrigins,
    alignment: Alignment,
    localisation: Localisation,
    detected: Detected,
    decision: Decision,
    timings: dict[str, float],
    extra_params: Mapping[str, Any] | None = None,
) -> ComparisonResult:
    """The result of one comparison from its stages' outputs.

    ``extra_params`` are reported among the parameters in effect, after the decision rule (a
    tiled comparison's memory budget).

    Returns
    -------
    ComparisonResult
        Regions and origins in file coordinates, per-point arrays in source order.
    """
    reference, scan, local_origin = loaded.reference, loaded.scan, loaded.local_origin
    visibility = visibility_report(origins, localisation)
    calibration = CalibrationReport(
        detector=dict(detected.detection.calibration),
        compared_points=detected.compared_points,
        site=decision.site,
        visibility=visibility,  # stored with a job's result (the API shows it)
        decision=decision,
    )
    transform = alignment.registration.transform
    return ComparisonResult(
        method=loaded.method,
        variant=loaded.variant,
        params=effective_params(loaded, extra_params),
        score=float(detected.detection.score),
        threshold=float(detected.detection.threshold),
        changed=decision.changed,
        calibration=calibration,
        registration=alignment.report,
        regions=[region_summary(region, local_origin) for region in localisation.regions],
        uncertain_regions=[
            region_summary(region, local_origin) for region in localisation.uncertain_regions
        ],
        n_reference=len(reference),
        n_scan=len(scan),
        reference_label=_in_file_order(
            reference, localisation.reference_label.astype(np.int8, copy=False), LABEL_UNOBSERVED
        ),
        scan_label=_in_file_order(
            scan, localisation.scan_label.astype(np.int8, copy=False), LABEL_UNOBSERVED
        ),
        reference_distance=_in_file_order(
            reference, localisation.reference_distance.astype(np.float32, copy=False), np.nan
        ),
        scan_distance=_in_file_order(
            scan, localisation.scan_distance.astype(np.float32, copy=False), np.nan
        ),
        reference_region=_in_file_order(
            reference, localisation.reference_region.astype(np.int32, copy=False), -1
        ),
        scan_region=_in_file_order(scan, localisation.scan_region.astype(np.int32, copy=False), -1),
        localisation=dict(localisation.parameters),
        timings=timings,
        sensor_origins={
            "reference": _entries(
                origins.reference.resolved.report(lambda origin: origin + local_origin)
            ),
            "scan": _entries(
                origins.scan.resolved.report(
                    lambda origin: to_scan_file(origin, transform, local_origin)
                )
            ),
        },
        warnings=[*origins.reference.resolved.warnings, *origins.scan.resolved.warnings],
        visibility=visibility,
    )


def _in_file_order(cloud: PointCloud, values: NDArray, fill: object) -> NDArray:
    """Per-point ``values`` in file order: themselves when no row was dropped (the stages'
    arrays are this comparison's own: no copy of a large pair's labels and distances), else
    :meth:`~app.core.cloud.PointCloud.to_source_order`."""
    return values if cloud.n_source == len(cloud) else cloud.to_source_order(values, fill)


def visibility_report(
    origins: SensorOrigins, localisation: Localisation
) -> dict[str, SideVisibility]:
    """What was found out about each cloud's sensors, and the visibility test it got."""
    return {
        side: SideVisibility.of(
            cloud.resolved.visibility_report(),
            localisation.parameters.get(f"{side}_visibility"),
        )
        for side, cloud in (("reference", origins.reference), ("scan", origins.scan))
    }


def _entries(report: list[dict[str, Any]]) -> list[SensorOriginEntry]:
    """:meth:`~app.core.origins.resolve.ResolvedOrigin.report`'s entries, typed."""
    return [SensorOriginEntry.of(entry) for entry in report]


def effective_params(
    loaded: LoadedPair, extra_params: Mapping[str, Any] | None = None
) -> dict[str, Any]:
    """Every parameter in effect: passing them back to ``compare`` replays the result."""
    settings = loaded.settings
    params: dict[str, Any] = {
        **settings.detector.get_params(),
        "align": settings.align,
        "registration": settings.registration,
        "localisation": settings.localisation,
        "decision": settings.decision,
        **(extra_params or {}),
    }
    for key, explicit in (
        ("reference_origin", settings.reference_origin),
        ("scan_origin", settings.scan_origin),
    ):
        if explicit is not None:  # as given: one origin, or a list of them
            params[key] = np.asarray(explicit, dtype=np.float64).tolist()
    if settings.recover_stations != "auto":
        params["recover_stations"] = settings.recover_stations
    if not settings.estimate_origins:
        params["estimate_origins"] = False
    return params


def to_scan_file(
    origin: NDArray[np.float64], transform: NDArray[np.float64], local_origin: NDArray
) -> NDArray[np.float64]:
    """Positions in the aligned local frame, in the scan file's coordinates, shape (3,)/(k, 3)."""
    moved = apply_transform(origin.reshape(-1, 3), np.linalg.inv(transform)) + local_origin
    return moved.reshape(origin.shape)
