"""The detector started beside the regions' clustering (app.core.comparison.early_detection)."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from app.core.cloud import PointCloud
from app.core.comparison import early_detection
from app.core.datasets.scenes import raycast_scene
from app.core.labels import LABEL_CHANGED, LABEL_UNCHANGED, LABEL_UNOBSERVED
from app.core.localise import changes
from app.core.pipeline import compare


@pytest.fixture(scope="module")
def box_pair():
    pair = raycast_scene(n_points=12_000, change="box", random_state=7)
    params = {
        "reference_origin": pair.reference_origin.tolist(),
        "scan_origin": pair.scan_origin.tolist(),
    }
    return PointCloud.from_array(pair.reference), PointCloud.from_array(pair.scan), params


def test_the_detector_runs_beside_the_regions_with_the_serial_result(monkeypatch, box_pair):
    """With two threads the detection is under way while the localiser clusters its regions
    (it started from the labels before them); the result is the one-thread comparison's."""
    reference, scan, params = box_pair
    one = compare(reference, scan, params=params, threads=1)
    events: list[str] = []
    find_regions = changes.find_regions
    detect_change = early_detection.detect_change

    def regions(*args, **kwargs):
        events.append("regions")
        return find_regions(*args, **kwargs)

    def detect(*args, **kwargs):
        events.append(f"detect on {threading.current_thread().name}")
        return detect_change(*args, **kwargs)

    monkeypatch.setattr(changes, "find_regions", regions)
    monkeypatch.setattr(early_detection, "detect_change", detect)
    two = compare(reference, scan, params=params, threads=2)
    assert "detect on early-detection" in events
    assert events.index("detect on early-detection") < len(events) - 1  # regions came after
    assert events[-1] == "regions"
    assert one.changed and one.regions
    assert two.score == one.score and two.threshold == one.threshold
    assert two.calibration == one.calibration
    for name in ("reference_label", "scan_label", "reference_region", "scan_region"):
        np.testing.assert_array_equal(getattr(two, name), getattr(one, name))
    assert two.localisation == one.localisation


def test_labels_that_observe_other_points_are_detected_again(monkeypatch, box_pair):
    """Should a later step of the localiser make a point unobserved (or observed), the early
    result is dropped and the detector runs again on the final labels: still the serial
    result."""
    reference, scan, params = box_pair
    one = compare(reference, scan, params=params, threads=1)
    hook_calls: list[int] = []
    start_for = early_detection.EarlyDetection.start_for

    def start_with_other_labels(self, aligned_scan):
        start = start_for(self, aligned_scan)

        def changed_start(reference_label, scan_label):
            hook_calls.append(len(reference_label))
            other = reference_label.copy()
            other[np.flatnonzero(other != LABEL_UNOBSERVED)[:50]] = LABEL_UNOBSERVED
            start(other, scan_label)

        return changed_start

    monkeypatch.setattr(early_detection.EarlyDetection, "start_for", start_with_other_labels)
    two = compare(reference, scan, params=params, threads=2)
    assert hook_calls == [len(reference.points)]
    assert two.score == one.score and two.calibration == one.calibration


def test_the_snapshot_compares_observed_points_only():
    """Changed points turned unchanged after the start keep the early result; a point turned
    unobserved does not."""
    started = np.array([LABEL_CHANGED, LABEL_UNCHANGED, LABEL_UNOBSERVED], dtype=np.int8)
    snapshot = early_detection.LabelsSnapshot(started, started)

    class Final:
        def __init__(self, reference_label, scan_label):
            self.reference_label, self.scan_label = reference_label, scan_label

    unchanged = np.array([LABEL_UNCHANGED, LABEL_UNCHANGED, LABEL_UNOBSERVED], dtype=np.int8)
    unobserved = np.array([LABEL_UNOBSERVED, LABEL_UNCHANGED, LABEL_UNOBSERVED], dtype=np.int8)
    assert snapshot.observes_as(Final(unchanged, started))
    assert not snapshot.observes_as(Final(started, unobserved))


def test_no_detection_thread_outlives_a_comparison_that_fails(monkeypatch, box_pair):
    """An error after the detection started (here in the regions step) is raised once the
    detection thread has ended."""
    reference, scan, params = box_pair

    def failing_regions(*args, **kwargs):
        raise RuntimeError("the regions failed")

    monkeypatch.setattr(changes, "find_regions", failing_regions)
    started = threading.Thread.start
    detection_threads: list[threading.Thread] = []

    def recorded_start(thread):
        if thread.name == "early-detection":
            detection_threads.append(thread)
        started(thread)

    monkeypatch.setattr(threading.Thread, "start", recorded_start)
    with pytest.raises(RuntimeError, match="the regions failed"):
        compare(reference, scan, params=params, threads=2)
    assert len(detection_threads) == 1
    assert not detection_threads[0].is_alive()
