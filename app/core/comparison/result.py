"""What one comparison produced: :class:`ComparisonResult` and its :class:`RegionSummary`."""

from __future__ import annotations

import zipfile
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.core.comparison.reports import (
    CalibrationReport,
    RegistrationReport,
    SensorOriginEntry,
    SideVisibility,
)
from app.core.explanation import Explanation, explain_comparison
from app.core.jsonable import json_safe
from app.core.labels import LABEL_CHANGED, LABEL_UNCHANGED, LABEL_UNOBSERVED
from app.core.quality import QualityWarning, quality_warnings

LABELS_COMPRESS_LEVEL = 1
"""zlib level of the labels file (:meth:`ComparisonResult.write_labels_npz`)."""


@dataclass(frozen=True)
class RegionSummary:
    """One connected cluster of changed points, in file coordinates of the reference frame."""

    kind: str  # "added" (in the scan, not in the reference) or "removed"
    n_points: int
    centroid: list[float]
    bbox_min: list[float]
    bbox_max: list[float]
    mean_distance: float
    max_distance: float
    evidence: str = "seen_empty"  # seen_empty | surface_moved | no_coverage
    confidence: float = 1.0

    def to_json_dict(self) -> dict[str, Any]:
        """Plain JSON types."""
        return {
            "kind": self.kind,
            "n_points": self.n_points,
            "centroid": self.centroid,
            "bbox_min": self.bbox_min,
            "bbox_max": self.bbox_max,
            "mean_distance": self.mean_distance,
            "max_distance": self.max_distance,
            "evidence": self.evidence,
            "confidence": self.confidence,
        }


def region_summary(region: Any, local_origin: NDArray[np.float64]) -> RegionSummary:
    """A localised region (:class:`~app.core.localise.ChangedRegion`) in file coordinates
    (the local origin, shape (3,), added back)."""
    return RegionSummary(
        kind=region.kind,
        n_points=int(region.n_points),
        centroid=(np.asarray(region.centroid) + local_origin).tolist(),
        bbox_min=(np.asarray(region.bbox_min) + local_origin).tolist(),
        bbox_max=(np.asarray(region.bbox_max) + local_origin).tolist(),
        mean_distance=float(region.mean_distance),
        max_distance=float(region.max_distance),
        evidence=str(region.evidence),
        confidence=round(float(region.confidence), 3),
    )


@dataclass(frozen=True)
class ComparisonResult:
    """Everything one comparison produced.

    Per-point arrays have one entry per row of the source file (points dropped on load keep
    their place): labels are 0 unchanged, 1 changed, -1 unobserved or dropped; distances are
    NaN there.  ``reference_region``/``scan_region`` index ``regions`` (-1: none).
    ``visibility`` says per cloud where its origins came from (``"origins"``: given, file,
    estimated, recovered or none), whether its sampling was measured to be a lidar's
    (``lidar_like``, with its figures) and stations searched (``stations_recovered``), whether
    it is a merged lidar cloud whose stations are unknown (``stations_unknown``), and the
    visibility test its change candidates got (``test``: ray, coverage or surfaces).
    """

    method: str
    variant: str
    params: dict[str, Any]
    score: float
    threshold: float
    changed: bool
    calibration: CalibrationReport
    registration: RegistrationReport
    regions: list[RegionSummary]
    n_reference: int
    n_scan: int
    reference_label: NDArray[np.int8]
    scan_label: NDArray[np.int8]
    reference_distance: NDArray[np.float32]
    scan_distance: NDArray[np.float32]
    reference_region: NDArray[np.int32]
    scan_region: NDArray[np.int32]
    localisation: dict[str, Any] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    sensor_origins: dict[str, list[SensorOriginEntry]] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    visibility: dict[str, SideVisibility] = field(default_factory=dict)
    uncertain_regions: list[RegionSummary] = field(default_factory=list)

    def label_counts(self) -> dict[str, dict[str, int]]:
        """How many points of each cloud are unchanged, changed and unobserved."""

        def counts(labels: NDArray[np.int8]) -> dict[str, int]:
            return {
                "unchanged": int(np.count_nonzero(labels == LABEL_UNCHANGED)),
                "changed": int(np.count_nonzero(labels == LABEL_CHANGED)),
                "unobserved": int(np.count_nonzero(labels == LABEL_UNOBSERVED)),
            }

        return {"reference": counts(self.reference_label), "scan": counts(self.scan_label)}

    def to_json_dict(self) -> dict[str, Any]:
        """The JSON object printed by ``scandiff compare --json`` (non-finite numbers: null)."""
        return json_safe(
            {
                "method": self.method,
                "variant": self.variant,
                "params": self.params,
                "score": self.score,
                "threshold": self.threshold,
                "changed": self.changed,
                "calibration": self.calibration.to_json_dict(),
                "registration": self.registration.to_json_dict(),
                "regions": [region.to_json_dict() for region in self.regions],
                "n_regions": len(self.regions),
                "uncertain_regions": [region.to_json_dict() for region in self.uncertain_regions],
                "n_reference": self.n_reference,
                "n_scan": self.n_scan,
                "label_counts": self.label_counts(),
                "localisation": self.localisation,
                "timings": self.timings,
                "sensor_origins": self.sensor_origins_json(),
                "warnings": self.warnings,
                "visibility": self.visibility_json(),
                "quality_warnings": [warning.to_json_dict() for warning in self.quality_warnings],
                "explanation": self.explanation.to_json_dict(),
            }
        )

    def sensor_origins_json(self) -> dict[str, list[dict[str, Any]]]:
        """``sensor_origins`` as stored: per side, its entries' JSON objects."""
        return {
            side: [entry.to_json_dict() for entry in entries]
            for side, entries in self.sensor_origins.items()
        }

    def visibility_json(self) -> dict[str, dict[str, Any]]:
        """``visibility`` as stored: per side, its JSON object."""
        return {side: seen.to_json_dict() for side, seen in self.visibility.items()}

    @cached_property
    def quality_warnings(self) -> list[QualityWarning]:
        """Every warning :func:`app.core.quality.quality_warnings` tells from this result
        (computed once; a result made with :func:`dataclasses.replace` computes its own)."""
        return quality_warnings(self)

    @cached_property
    def explanation(self) -> Explanation:
        """Why it decided what it did (:func:`app.core.explanation.explain_comparison`),
        computed once."""
        return explain_comparison(self)

    def write_labels_npz(self, path: str | Path) -> None:
        """Write ``reference_changed``, ``scan_changed``, ``reference_label``, ``scan_label``.

        A ``numpy.savez_compressed`` file (``numpy.load`` reads it), deflated at level 1: a
        third of the time of its default level for 1.5x the bytes (labels compress well
        either way).
        """
        arrays = {
            "reference_changed": self.reference_label == LABEL_CHANGED,
            "scan_changed": self.scan_label == LABEL_CHANGED,
            "reference_label": self.reference_label.astype(np.int8),
            "scan_label": self.scan_label.astype(np.int8),
        }
        with zipfile.ZipFile(
            path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=LABELS_COMPRESS_LEVEL
        ) as archive:
            for name, array in arrays.items():
                with archive.open(f"{name}.npy", "w", force_zip64=True) as member:
                    np.lib.format.write_array(member, array, allow_pickle=False)
