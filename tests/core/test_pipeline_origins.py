"""compare() resolves each side's sensor origin (given > file > estimated > none) and says so."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.cloud import PointCloud
from app.core.datasets.lidar import lidar_pair
from app.core.errors import InputError
from app.core.labels import LABEL_CHANGED
from app.core.pipeline import compare

STEP = 0.8


def _iou(result, pair) -> float:
    predicted = np.concatenate(
        [
            result.reference_label[pair.reference_observed] == LABEL_CHANGED,
            result.scan_label[pair.scan_observed] == LABEL_CHANGED,
        ]
    )
    truth = np.concatenate(
        [pair.reference_changed[pair.reference_observed], pair.scan_changed[pair.scan_observed]]
    )
    return float(np.count_nonzero(predicted & truth) / max(np.count_nonzero(predicted | truth), 1))


@pytest.fixture(scope="module")
def misaligned_pair():
    return lidar_pair(
        layout="room", change="added", angular_step_deg=STEP, misaligned=True, random_state=31
    )


@pytest.fixture(scope="module")
def without_origins(misaligned_pair):
    pair = misaligned_pair
    return compare(PointCloud.from_array(pair.reference), PointCloud.from_array(pair.scan))


def test_missing_origins_are_estimated_in_each_files_frame(misaligned_pair, without_origins):
    origins = without_origins.to_json_dict()["sensor_origins"]
    for side, truth in (
        ("reference", misaligned_pair.reference_origin),
        ("scan", misaligned_pair.scan_origin),
    ):
        (entry,) = origins[side]
        assert entry["source"] == "estimated" and entry["confidence"] >= 0.5
        assert np.linalg.norm(np.array(entry["origin"]) - truth) < 0.03
    assert without_origins.warnings == []


def test_estimated_origins_localise_as_well_as_given_ones(misaligned_pair, without_origins):
    pair = misaligned_pair
    given = compare(
        PointCloud.from_array(pair.reference),
        PointCloud.from_array(pair.scan),
        params={
            "reference_origin": pair.reference_origin.tolist(),
            "scan_origin": pair.scan_origin.tolist(),
        },
    )
    assert [entry.source for entry in given.sensor_origins["reference"]] == ["given"]
    assert given.changed and without_origins.changed
    assert _iou(without_origins, pair) >= _iou(given, pair) - 0.05
    assert _iou(without_origins, pair) >= 0.8


def test_a_contradicted_file_origin_warns_and_the_estimate_takes_over(misaligned_pair):
    pair = misaligned_pair
    result = compare(
        PointCloud.from_array(pair.reference, sensor_origin=np.array([0.0, 0.0, 1.2])),
        PointCloud.from_array(pair.scan, sensor_origin=pair.scan_origin),
    )
    json_result = result.to_json_dict()
    (reference_entry,) = json_result["sensor_origins"]["reference"]
    assert reference_entry["source"] == "estimated"
    assert np.linalg.norm(np.array(reference_entry["origin"]) - pair.reference_origin) < 0.03
    assert json_result["sensor_origins"]["scan"][0]["source"] == "file"
    assert len(json_result["warnings"]) == 1
    assert "reference's file sensor origin" in json_result["warnings"][0]


def test_unchanged_pair_without_origins_has_no_changed_region() -> None:
    pair = lidar_pair(layout="corridor", change="none", angular_step_deg=STEP, random_state=32)
    result = compare(PointCloud.from_array(pair.reference), PointCloud.from_array(pair.scan))
    assert result.sensor_origins["reference"][0].source == "estimated"
    assert not result.changed and result.regions == []


def test_estimation_can_be_turned_off_and_is_validated(misaligned_pair) -> None:
    pair = misaligned_pair
    result = compare(
        PointCloud.from_array(pair.reference),
        PointCloud.from_array(pair.scan),
        params={"estimate_origins": False},
    )
    assert result.sensor_origins == {"reference": [], "scan": []}
    assert result.params["estimate_origins"] is False
    with pytest.raises(InputError, match="estimate_origins"):
        compare(
            PointCloud.from_array(pair.reference),
            PointCloud.from_array(pair.scan),
            params={"estimate_origins": "yes"},
        )
