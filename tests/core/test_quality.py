"""Quality warnings on every result: registration, overlap, sensor origins; paper aliases."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.cloud import PointCloud
from app.core.comparison.reports import QualityWarning
from app.core.datasets.scenes import raycast_scene
from app.core.detectors import METHOD_ALIASES, METHODS, canonical_method, make_detector
from app.core.errors import InputError
from app.core.pipeline import compare
from app.core.quality import (
    FIX_ACTIONS,
    LARGE_ROTATION_DEGREES,
    LARGE_TRANSLATION_METRES,
    LOW_FITNESS,
    LOW_OVERLAP_FRACTION,
    origin_warnings,
    overlap_warnings,
    quality_warnings,
    registration_warnings,
)
from app.core.registration import apply_transform


def codes(warnings: list[QualityWarning]) -> list[str]:
    return [warning.code for warning in warnings]


def test_a_good_alignment_has_no_warning() -> None:
    report = {"fitness": 0.95, "rotation_degrees": 0.3, "translation_m": 0.05, "enabled": True}
    assert registration_warnings(report) == []


def test_low_fitness_and_a_large_correction_are_warned_with_units() -> None:
    report = {
        "fitness": LOW_FITNESS - 0.2,
        "rotation_degrees": LARGE_ROTATION_DEGREES + 2.1,
        "translation_m": LARGE_TRANSLATION_METRES + 1.0,
        "max_correspondence_distance": 0.4,
        "enabled": True,
    }
    warnings = registration_warnings(report)
    assert codes(warnings) == ["low_registration_fitness", "large_rotation", "large_translation"]
    fitness, rotation, translation = warnings
    assert fitness.value == report["fitness"] and fitness.limit == LOW_FITNESS
    assert "within 0.4 m of the reference" in fitness.message
    assert f"{report['rotation_degrees']:.1f} degrees" in rotation.message
    assert rotation.unit == "degrees"
    assert f"{report['translation_m']:.2f} m" in translation.message
    for warning in warnings:  # one sentence, no interface's knob; the fix as an action
        message = warning.message
        assert message.endswith(".") and message.count(". ") == 0 and "; " not in message
        assert "--" not in message and '"align"' not in message
        assert warning.action in FIX_ACTIONS
        assert warning.to_json_dict()["detail"]["value"] == warning.value
        assert warning.explanation
    for warning in (rotation, translation):  # no stale "moving sensor's frame" advice
        assert warning.action == "check_alignment"
        assert "moving sensor" not in str(warning)


def test_limits_are_parameters() -> None:
    report = {"fitness": 0.95, "rotation_degrees": 1.0, "translation_m": 0.2}
    assert codes(registration_warnings(report, large_rotation_degrees=0.5)) == ["large_rotation"]
    assert codes(registration_warnings(report, low_fitness=0.99)) == ["low_registration_fitness"]


def test_without_alignment_only_the_fit_is_checked() -> None:
    report = {"fitness": 0.2, "rotation_degrees": 0.0, "translation_m": 0.0, "enabled": False}
    (warning,) = registration_warnings(report)
    assert warning.code == "low_registration_fitness"
    assert "(not aligned)" in warning.message


def test_low_overlap_names_the_less_observed_cloud() -> None:
    reference = np.zeros(100, dtype=np.int8)
    scan = np.zeros(200, dtype=np.int8)
    assert overlap_warnings(reference, scan) == []
    unobserved = int(200 * (1 - LOW_OVERLAP_FRACTION)) + 20
    scan[:unobserved] = -1
    (warning,) = overlap_warnings(reference, scan)
    assert warning.code == "low_overlap"
    assert warning.side == "scan"
    assert warning.value == pytest.approx(1 - unobserved / 200)
    assert "of the scan's points were observed by the reference" in warning.message


def test_origin_warnings_unknown_and_contradicted() -> None:
    known = [{"origin": [0.0, 0.0, 1.0], "source": "estimated", "confidence": 0.9}]
    assert origin_warnings({"reference": known, "scan": known}) == []
    warnings = origin_warnings({"reference": known, "scan": []}, ["the scan's file origin ..."])
    assert codes(warnings) == ["sensor_origin", "sensor_origin_unknown"]
    assert warnings[0].explanation == "the scan's file origin ..."
    assert warnings[1].side == "scan"
    assert warnings[1].action == "give_sensor_origin"
    assert "sensor_origin=" not in warnings[1].message and "--" not in warnings[1].message
    assert origin_warnings(None) == []  # not reported: nothing to say


def test_points_outside_a_trajectorys_time_span_are_warned() -> None:
    covered = {"source": "trajectory", "poses": 40, "time_span": [10.0, 20.0], "points_outside": 0}
    partly = {**covered, "points_outside": 1234}
    assert origin_warnings({"reference": [covered], "scan": [covered, "junk"]}) == []

    (warning,) = origin_warnings({"reference": [covered], "scan": [partly]})

    assert warning.code == "trajectory_time_span" and warning.side == "scan"
    assert warning.value == 1234 and warning.action == "check_trajectory"
    assert "1,234 of the scan's points have times outside" in warning.message
    assert "10.000..20.000 s" in warning.message


@pytest.fixture(scope="module")
def box_pair():
    return raycast_scene(n_points=12_000, change="box", random_state=3)


def test_a_result_without_origins_and_turned_far_is_warned(box_pair) -> None:
    angle = np.radians(LARGE_ROTATION_DEGREES + 3.0)
    turn = np.eye(4)
    turn[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
    turn[:3, 3] = [LARGE_TRANSLATION_METRES + 0.3, 0.0, 0.0]
    scan = PointCloud.from_array(apply_transform(box_pair.scan, turn))
    result = compare(
        PointCloud.from_array(box_pair.reference),
        scan,
        params={"estimate_origins": False},
    )
    found = codes(quality_warnings(result))
    assert "large_rotation" in found and "large_translation" in found
    assert found.count("sensor_origin_unknown") == 2
    assert result.registration.rotation_degrees > LARGE_ROTATION_DEGREES
    assert result.to_json_dict()["quality_warnings"] == [
        warning.to_json_dict() for warning in quality_warnings(result)
    ]
    assert result.quality_warnings == quality_warnings(result)  # computed once, the same


def test_a_clean_rescan_with_origins_is_not_warned(box_pair) -> None:
    result = compare(
        PointCloud.from_array(box_pair.reference, sensor_origin=box_pair.reference_origin),
        PointCloud.from_array(box_pair.scan, sensor_origin=box_pair.scan_origin),
    )
    assert quality_warnings(result) == [], result.registration


@pytest.mark.parametrize(
    ("name", "canonical"),
    [
        ("pe", "planes"),
        ("PE-EMD", "planes"),
        ("Pe-Emd", "planes"),
        ("pca-emd", "pca"),
        ("PCA", "pca"),
        ("GMM-EMD", "gmm"),
        (" gmm ", "gmm"),
        ("planes", "planes"),
    ],
)
def test_the_papers_names_are_aliases(name: str, canonical: str) -> None:
    assert canonical_method(name) == canonical
    assert type(make_detector(name)) is type(make_detector(canonical))


def test_every_alias_names_a_method_and_unknown_names_list_them() -> None:
    assert set(METHOD_ALIASES.values()) <= set(METHODS)
    with pytest.raises(InputError, match=r"unknown detector method 'pe-gmm'.*pe-emd"):
        canonical_method("pe-gmm")


def test_a_comparison_by_alias_reports_the_canonical_name(box_pair) -> None:
    cloud = PointCloud.from_array(box_pair.reference)
    result = compare(cloud, cloud, method="PE-EMD")
    assert result.method == "planes"
