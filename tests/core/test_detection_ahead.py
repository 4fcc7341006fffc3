"""The detector's score beside the region clustering: the localiser hands over the observed
points before it clusters (``localise_changes(on_observed=...)``) and the pipeline scores them
on a thread of its own (``DetectionAhead``); the result is the one of scoring afterwards."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from app.core.cloud import PointCloud
from app.core.comparison import decide
from app.core.datasets.scenes import raycast_scene
from app.core.labels import LABEL_UNOBSERVED
from app.core.localise import changes
from app.core.localise.epoch import EpochCloud
from app.core.pipeline import compare


@pytest.fixture(scope="module")
def box_pair():
    pair = raycast_scene(n_points=20_000, change="box", random_state=3)
    return (
        PointCloud.from_array(pair.reference, sensor_origin=pair.reference_origin),
        PointCloud.from_array(pair.scan, sensor_origin=pair.scan_origin),
    )


def test_the_observed_points_are_handed_over_before_the_regions(box_pair, monkeypatch):
    events = []
    handed = []
    find_regions = changes.find_regions

    def recorded_find_regions(*args, **kwargs):
        events.append("regions")
        return find_regions(*args, **kwargs)

    def on_observed(reference_observed, scan_observed):
        events.append("observed")
        handed.append((reference_observed.copy(), scan_observed.copy()))

    monkeypatch.setattr(changes, "find_regions", recorded_find_regions)
    reference, scan = box_pair
    localisation = changes.localise_changes(
        EpochCloud(reference.points, origin=reference.sensor_origin),
        EpochCloud(scan.points, origin=scan.sensor_origin),
        threads=2,
        on_observed=on_observed,
    )
    assert events[0] == "observed" and events.count("observed") == 1 and "regions" in events
    ((reference_observed, scan_observed),) = handed
    assert np.array_equal(reference_observed, localisation.reference_label != LABEL_UNOBSERVED)
    assert np.array_equal(scan_observed, localisation.scan_label != LABEL_UNOBSERVED)
    assert not reference_observed.all() and reference_observed.any()


def test_two_threads_score_beside_the_regions_with_the_same_result(box_pair, monkeypatch):
    scored_on = []
    detect_observed = decide.detect_observed

    def recorded_detect_observed(*args, **kwargs):
        scored_on.append(threading.current_thread().name)
        return detect_observed(*args, **kwargs)

    monkeypatch.setattr(decide, "detect_observed", recorded_detect_observed)
    one = compare(*box_pair, threads=1)
    two = compare(*box_pair, threads=2)
    assert scored_on == ["MainThread", "detection"]
    assert two.score == one.score and two.threshold == one.threshold
    assert two.calibration == one.calibration and two.changed == one.changed
    assert np.array_equal(two.scan_label, one.scan_label)
    assert two.timings["detect"] > 0


def test_a_failed_detection_ahead_is_raised_by_the_comparison(box_pair, monkeypatch):
    def failing(*args, **kwargs):
        raise RuntimeError("the detector failed")

    monkeypatch.setattr(decide, "detect_observed", failing)
    with pytest.raises(RuntimeError, match="the detector failed"):
        compare(*box_pair, threads=2)
    assert not [thread for thread in threading.enumerate() if thread.name == "detection"]


def test_a_failed_localisation_waits_for_the_detection_it_started(box_pair, monkeypatch):
    def failing(*args, **kwargs):
        raise RuntimeError("the clustering failed")

    detect_observed = decide.detect_observed

    def slow_detect_observed(*args, **kwargs):
        time.sleep(0.5)  # still running when the clustering fails
        return detect_observed(*args, **kwargs)

    monkeypatch.setattr(changes, "find_regions", failing)
    monkeypatch.setattr(decide, "detect_observed", slow_detect_observed)
    with pytest.raises(RuntimeError, match="the clustering failed"):
        compare(*box_pair, threads=2)
    assert not [thread for thread in threading.enumerate() if thread.name == "detection"]
