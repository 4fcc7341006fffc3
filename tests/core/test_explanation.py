"""Every decision explains itself: the structured explanation and its one line of text."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.cloud import PointCloud
from app.core.comparison.reports import LargestRegion
from app.core.datasets.scenes import raycast_scene
from app.core.explanation import explain_comparison, explain_decision
from app.core.pipeline import RegionSummary, compare
from app.core.registration import apply_transform


def region(kind: str, n_points: int, low: list[float], high: list[float]) -> RegionSummary:
    centre = [(a + b) / 2 for a, b in zip(low, high, strict=True)]
    return RegionSummary(kind, n_points, centre, low, high, 0.2, 0.4)


def test_regions_decide_although_the_score_is_below_the_threshold() -> None:
    regions = [
        region("added", 1282, [0.0, 0.0, 0.0], [0.82, 0.82, 1.0]),
        region("removed", 300, [5.0, 5.0, 0.0], [5.1, 5.2, 0.3]),
    ]
    explanation = explain_decision(
        changed=True,
        rule="regions",
        score=0.03698,
        threshold=0.04244,
        detector_changed=False,
        regions=regions,
        min_region_points=200,
    )
    assert explanation.decision == "changed"
    assert explanation.decided_by == "regions"
    assert explanation.n_regions == 2
    assert explanation.n_region_points == 1582
    assert explanation.largest_region == LargestRegion(
        index=0, kind="added", n_points=1282, size_m=(0.82, 0.82, 1.0)
    )
    assert explanation.to_json_dict()["largest_region"] == {
        "index": 0,
        "kind": "added",
        "n_points": 1282,
        "size_m": [0.82, 0.82, 1.0],
    }
    assert explanation.agrees is False
    text = explanation.text
    assert text.startswith("changed: 2 regions of 1,582 points (>= 200 each)")
    assert "largest 0.82 x 0.82 x 1.00 m" in text
    assert "score 0.037 is below its threshold 0.0424" in text
    assert "the regions decide" in text


def test_one_region_is_described_without_largest() -> None:
    text = explain_decision(
        changed=True,
        rule="regions",
        score=0.16,
        threshold=0.65,
        detector_changed=False,
        regions=[region("added", 250, [1.0, 2.0, 3.0], [1.5, 2.25, 4.0])],
        min_region_points=200,
    ).text
    assert text.startswith("changed: 1 region of 250 points (>= 200 each), 0.50 x 0.25 x 1.00 m;")


def test_no_change_names_the_dropped_clusters_and_the_detector() -> None:
    explanation = explain_decision(
        changed=False,
        rule="regions",
        score=0.9,
        threshold=0.5,
        detector_changed=True,
        regions=[],
        min_region_points=120,
        dropped_clusters=3,
    )
    assert explanation.decision == "unchanged"
    assert explanation.largest_region is None
    assert explanation.agrees is False
    assert explanation.text == (
        "no change: no region of changed points (>= 120 each) (3 smaller clusters dropped); "
        "the detector's score 0.9 is above its threshold 0.5 (the regions decide)"
    )


@pytest.mark.parametrize(
    ("rule", "changed", "decided_by"),
    [("detector", True, "detector"), ("either", True, "regions and detector")],
)
def test_other_rules_say_what_decides(rule: str, changed: bool, decided_by: str) -> None:
    explanation = explain_decision(
        changed=changed,
        rule=rule,
        score=0.9,
        threshold=0.5,
        detector_changed=None,  # unknown: taken from score > threshold
        regions=[region("removed", 40, [0.0, 0.0, 0.0], [1.0, 1.0, 1.0])],
    )
    assert explanation.detector_changed is True
    assert explanation.decided_by == decided_by
    assert explanation.agrees is True
    if rule == "detector":
        assert explanation.text.startswith("changed: the detector's score 0.9 is above")
        assert "localisation found 1 region of 40 points" in explanation.text


def test_regions_as_mappings_like_stored_rows() -> None:
    rows = [{"kind": "removed", "n_points": 10, "bbox_min": [0, 0, 0], "bbox_max": [2, 1, 1]}]
    explanation = explain_decision(
        changed=True,
        rule="regions",
        score=None,
        threshold=None,
        detector_changed=None,
        regions=rows,
    )
    assert explanation.largest_region.size_m == (2.0, 1.0, 1.0)
    assert "the detector's score is unknown" in explanation.text


@pytest.fixture(scope="module")
def box_pair():
    return raycast_scene(n_points=12_000, change="box", random_state=3)


def test_a_real_comparison_explains_its_own_numbers(box_pair) -> None:
    pair = box_pair
    result = compare(
        PointCloud.from_array(pair.reference, sensor_origin=pair.reference_origin),
        PointCloud.from_array(pair.scan, sensor_origin=pair.scan_origin),
    )
    explanation = explain_comparison(result)
    assert explanation.to_json_dict() == result.to_json_dict()["explanation"]
    assert explanation == result.explanation  # computed once, the same
    assert explanation.decision == ("changed" if result.changed else "unchanged")
    assert explanation.rule == result.calibration.decision.rule
    assert explanation.n_regions == len(result.regions)
    assert explanation.n_region_points == sum(r.n_points for r in result.regions)
    assert explanation.min_region_points == result.localisation["min_region_points"]
    assert explanation.detector_changed == result.calibration.decision.detector_changed
    assert f"{len(result.regions)} region" in explanation.text
    assert f"{result.score:.3g}" in explanation.text


def test_an_unchanged_copy_explains_no_change(box_pair) -> None:
    cloud = PointCloud.from_array(box_pair.reference)
    moved = apply_transform(box_pair.reference, np.eye(4))
    result = compare(cloud, PointCloud.from_array(moved))
    explanation = explain_comparison(result)
    assert not result.changed
    assert explanation.decision == "unchanged"
    assert explanation.text.startswith("no change: no region of changed points")


@pytest.mark.parametrize(("fires", "relation"), [(False, "not above"), (True, "above")])
def test_a_site_threshold_that_took_part_is_named(fires: bool, relation: str) -> None:
    site_test = {
        "statistic": "largest_region_extent_m",
        "value": 0.74,
        "comparison": ">",
        "threshold": 0.91,
        "source": "site",
        "fires": fires,
    }
    explanation = explain_decision(
        changed=fires,
        rule="regions",
        score=0.2,
        threshold=0.1,
        detector_changed=True,
        regions=[region("added", 120, [0.0, 0.0, 0.0], [0.4, 0.4, 0.5])],
        site_test=site_test,
    )
    assert explanation.site_test == site_test
    assert explanation.text.startswith("changed: " if fires else "no change: ")
    assert explanation.text.endswith(
        f"the largest region's extent 0.74 m is {relation} the site's learned threshold "
        "0.91 m (from reviews)"
    )
