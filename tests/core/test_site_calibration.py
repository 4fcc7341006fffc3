"""The per-site calibration rule: a split-conformal upper bound, and the decision applying it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.core.cloud import PointCloud
from app.core.datasets.site import site_visit
from app.core.explanation import explain_comparison, explain_decision
from app.core.pipeline import compare
from app.core.site_calibration import (
    DecisionInputs,
    ReviewedSample,
    conformal_rank,
    conformal_upper_bound,
    decide,
    largest_extent,
    learn_site_calibration,
    minimum_samples,
)

TRIALS = 20_000


def exceedance_rate(draw, n_samples: int, false_alarm_rate: float, seed: int) -> float:
    """How often one more exchangeable value exceeds the bound of ``n_samples`` values."""
    rng = np.random.default_rng(seed)
    values = draw(rng, (TRIALS, n_samples + 1))
    exceeded = [row[-1] > conformal_upper_bound(row[:-1], false_alarm_rate) for row in values]
    return float(np.mean(exceeded))


@pytest.mark.parametrize(
    ("name", "draw"),
    [
        ("lognormal", lambda rng, shape: rng.lognormal(0.0, 1.0, shape)),
        ("heavy tail", lambda rng, shape: rng.pareto(1.5, shape)),
        # region sizes: integers with ties, mostly 0 (no region), sometimes a cluster
        ("integer counts", lambda rng, shape: rng.poisson(3, shape) * (rng.random(shape) < 0.6)),
    ],
)
@pytest.mark.parametrize(("n_samples", "false_alarm_rate"), [(5, 0.2), (9, 0.1), (19, 0.2)])
def test_bound_holds_at_the_stated_rate_on_exchangeable_samples(
    name: str, draw, n_samples: int, false_alarm_rate: float
) -> None:
    rate = exceedance_rate(draw, n_samples, false_alarm_rate, seed=n_samples)
    standard_error = math.sqrt(false_alarm_rate * (1 - false_alarm_rate) / TRIALS)
    assert rate <= false_alarm_rate + 4 * standard_error, (name, rate)
    if name != "integer counts":  # continuous values: the bound is also tight
        slack = 1.0 / (n_samples + 1)
        assert rate >= false_alarm_rate - slack - 4 * standard_error, (name, rate)


def test_bound_is_the_conformal_order_statistic() -> None:
    values = [5.0, 1.0, 4.0, 2.0, 3.0]
    # n = 5, alpha = 0.2: k = ceil(6 * 0.8) = 5, the largest
    assert conformal_rank(5, 0.2) == 5
    assert conformal_upper_bound(values, 0.2) == 5.0
    # n = 5, alpha = 0.5: k = 3, the median
    assert conformal_upper_bound(values, 0.5) == 3.0
    # too few values for alpha = 0.1 (k = 6 > 5): no finite bound
    assert conformal_upper_bound(values, 0.1) == math.inf
    assert minimum_samples(0.1) == 9 and minimum_samples(0.2) == 4
    assert conformal_rank(19, 0.05) == 19  # no float round-up to 20
    with pytest.raises(ValueError, match="false_alarm_rate"):
        conformal_rank(5, 1.5)
    with pytest.raises(ValueError, match="finite"):
        conformal_upper_bound([1.0, math.nan], 0.2)


def samples(sizes: list[float], scores: list[float] | None = None) -> list[ReviewedSample]:
    scores = scores or [0.1] * len(sizes)
    return [
        ReviewedSample(job_id=f"job{index}", score=score, largest_region_extent_m=size)
        for index, (size, score) in enumerate(zip(sizes, scores, strict=True))
    ]


def test_learning_needs_the_minimum_count_then_states_its_provenance() -> None:
    learning = learn_site_calibration(
        samples([0.4, 0.8, 0.35]),
        method="pca",
        variant="improved",
        false_alarm_rate=0.2,
        min_samples=5,
    )
    assert learning["status"] == "learning" and learning["thresholds"] is None
    assert (learning["n_samples"], learning["min_samples"]) == (3, 5)
    learned = learn_site_calibration(
        samples([0.4, 0.8, 0.35, 0.6, 0.5], [0.1, 0.3, 0.2, 0.05, 0.15]),
        method="pca",
        variant="improved",
        false_alarm_rate=0.2,
        min_samples=5,
    )
    assert learned["status"] == "learned" and learned["rank"] == 5
    assert learned["thresholds"] == {"largest_region_extent_m": 0.8, "score": 0.3}
    assert learned["source_job_ids"] == [f"job{index}" for index in range(5)]
    assert learned["rule"].startswith("split-conformal") and learned["false_alarm_rate"] == 0.2
    # a rate that needs more samples than the setting asks for raises the minimum
    strict = learn_site_calibration(
        samples([1] * 5), method="pca", variant="improved", false_alarm_rate=0.05, min_samples=5
    )
    assert strict["status"] == "learning" and strict["min_samples"] == 19


def inputs(**overrides) -> DecisionInputs:
    values = {
        "rule": "regions",
        "method": "pca",
        "variant": "improved",
        "score": 0.2,
        "detector_threshold": 0.25,
        "n_regions": 2,
        "largest_region_extent_m": 0.7,
        "min_region_points": 11,
    }
    return DecisionInputs(**{**values, **overrides})


def site(largest: float, score: float, **fields) -> dict:
    return {
        "status": "learned",
        "method": "pca",
        "variant": "improved",
        "n_samples": 5,
        "thresholds": {"largest_region_extent_m": largest, "score": score},
        **fields,
    }


def test_decision_without_a_site_calibration_is_the_default_rule() -> None:
    changed, tests, provenance = decide(inputs(), None)
    assert changed and provenance["applied"] is False and "no reviewed jobs" in provenance["reason"]
    assert tests == [
        {
            "statistic": "largest_region_extent_m",
            "value": 0.7,
            "comparison": ">",
            "threshold": 0.0,
            "source": "default",
            "n_regions": 2,
            "min_region_points": 11,
            "fires": True,
        }
    ]
    changed, tests, _ = decide(inputs(n_regions=0, largest_region_extent_m=0.0), None)
    assert not changed and tests[0]["value"] == 0.0


def test_a_learned_threshold_silences_the_nuisance_and_keeps_larger_changes() -> None:
    learned = site(0.87, 0.31)
    changed, tests, provenance = decide(inputs(largest_region_extent_m=0.7), learned)
    assert not changed and provenance["applied"] is True
    assert (tests[0]["source"], tests[0]["threshold"], tests[0]["comparison"]) == (
        "site",
        0.87,
        ">",
    )
    changed, _, _ = decide(inputs(largest_region_extent_m=1.7), learned)
    assert changed
    # learned on reviewed-unchanged jobs only (no region: 0 m): the default rule stays
    changed, tests, _ = decide(inputs(), site(0.0, 0.0))
    assert changed and tests[0]["source"] == "default"


def test_either_rule_tests_both_statistics_and_detector_rule_the_score() -> None:
    learned = site(0.87, 0.31)
    changed, tests, _ = decide(inputs(rule="either", score=0.3), learned)
    assert [test["statistic"] for test in tests] == ["largest_region_extent_m", "score"]
    assert not changed and tests[1]["threshold"] == 0.31
    changed, tests, _ = decide(inputs(rule="detector", score=0.4), learned)
    assert changed and [test["statistic"] for test in tests] == ["score"]


def test_calibration_of_another_detector_or_still_learning_is_not_applied() -> None:
    changed, _, provenance = decide(inputs(), site(0.87, 0.31, method="gmm"))
    assert changed and not provenance["applied"] and "gmm/improved" in provenance["reason"]
    learning = {"status": "learning", "n_samples": 2, "min_samples": 5, "thresholds": None}
    changed, _, provenance = decide(inputs(), learning)
    assert changed and not provenance["applied"] and "2 reviewed-null" in provenance["reason"]


def test_compare_applies_a_site_calibration_and_reports_it() -> None:
    reference = site_visit(bin_spot=5, n_points=8000, sensor_shift=0.0, random_state=1)
    visit = site_visit(bin_spot=1, n_points=8000, sensor_shift=0.5, random_state=2)
    clouds = [
        PointCloud.from_array(one.points, sensor_origin=one.sensor_origin)
        for one in (reference, visit)
    ]
    plain = compare(*clouds, method="pca")
    tests = plain.calibration.decision.tests
    assert plain.calibration.site.applied is False
    largest = largest_extent(plain.regions)
    assert plain.changed and largest > 0, "the moved bin should leave a region"
    assert tests[0].value == pytest.approx(largest)
    above = site(largest, 1e9, method="pca", variant="improved")
    calibrated = compare(*clouds, method="pca", site_calibration=above)
    assert calibrated.calibration.site.applied is True
    assert not calibrated.changed  # equal to the learned bound: not above it
    assert len(calibrated.regions) == len(plain.regions)  # the regions are still reported
    assert "learned threshold" not in explain_comparison(plain).text
    text = explain_comparison(calibrated).text
    assert text.startswith("no change: ") and "not above the site's learned threshold" in text


def test_largest_extent_is_the_diagonal_of_the_region_with_the_most_points() -> None:
    # the explanation's largest region (most points), not the widest box
    regions = [
        {
            "kind": "added",
            "n_points": 900,
            "bbox_min": [0.0, 0.0, 0.0],
            "bbox_max": [0.3, 0.4, 0.0],
        },
        {
            "kind": "removed",
            "n_points": 40,
            "bbox_min": [1.0, 1.0, 1.0],
            "bbox_max": [2.0, 3.0, 3.0],
        },
        {
            "kind": "added",
            "n_points": 900,
            "bbox_min": [0.0, 0.0, 0.0],
            "bbox_max": [6.0, 8.0, 0.0],
        },
    ]
    assert largest_extent(regions) == pytest.approx(0.5)
    explanation = explain_decision(
        changed=True,
        rule="regions",
        score=None,
        threshold=None,
        detector_changed=None,
        regions=regions,
    )
    assert explanation.largest_region.index == 0
    assert largest_extent(regions[1:]) == pytest.approx(10.0)
    assert largest_extent([]) == 0.0
