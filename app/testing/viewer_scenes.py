"""A synthetic pair compared as the worker compares it, and its 3D view's scene data."""

from __future__ import annotations

from app.core.cloud import PointCloud
from app.core.comparison.result import ComparisonResult
from app.core.datasets.scenes import SyntheticPair
from app.core.pipeline import compare
from app.viewer.scene import SceneData, build_scene_data


def compare_with_origins(pair: SyntheticPair) -> ComparisonResult:
    """``compare`` of ``pair`` with both sensor origins given, default detector."""
    return compare(
        PointCloud.from_array(pair.reference, sensor_origin=pair.reference_origin),
        PointCloud.from_array(pair.scan, sensor_origin=pair.scan_origin),
    )


def scene_of(pair: SyntheticPair, result: ComparisonResult) -> SceneData:
    """The scene the 3D view builds for ``result`` of ``pair`` (labels, distances, regions)."""
    return build_scene_data(
        pair.reference,
        pair.scan,
        reference_labels=result.reference_label,
        scan_labels=result.scan_label,
        reference_distances=result.reference_distance,
        scan_distances=result.scan_distance,
        transform=result.registration.transform,
        regions=result.to_json_dict()["regions"],
        min_region_points=result.localisation["min_region_points"],
    )
