"""The comparison pipeline's contract, over every detector and variant."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from app.core.cloud import PointCloud
from app.core.comparison import localise as localise_stage
from app.core.datasets.scenes import raycast_scene
from app.core.detectors import METHODS, VARIANTS
from app.core.errors import InputError
from app.core.labels import LABEL_CHANGED
from app.core.localise import neighbourhoods
from app.core.pipeline import compare
from app.core.registration import apply_transform

SCENE_POINTS = 20_000
SMALL_AHEAD_MIN_POINTS = 10_000
"""REFERENCE_AHEAD_MIN_POINTS in the run-ahead test: its scene is 15k points, not 55k."""


@pytest.fixture(scope="module")
def added_box_pair():
    return raycast_scene(n_points=SCENE_POINTS, change="box", random_state=3)


@pytest.fixture(scope="module")
def unchanged_pair():
    return raycast_scene(
        n_points=SCENE_POINTS, change="none", pose_error=(0.03, 0.4), random_state=4
    )


def rigid_transform(angle_degrees: float, translation: tuple[float, float, float]) -> np.ndarray:
    angle = np.radians(angle_degrees)
    transform = np.eye(4)
    transform[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
    transform[:3, 3] = translation
    return transform


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("method", METHODS)
def test_identical_clouds_score_near_zero_and_unchanged(method, variant, added_box_pair):
    cloud = PointCloud.from_array(added_box_pair.reference)
    result = compare(cloud, cloud, method=method, variant=variant)
    assert result.score <= 1e-6 + 1e-3 * abs(result.threshold)
    assert not result.changed
    assert result.regions == []
    assert np.count_nonzero(result.reference_label == LABEL_CHANGED) == 0


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("method", METHODS)
def test_rigidly_moved_copy_is_unchanged_after_alignment(method, variant, added_box_pair):
    reference = PointCloud.from_array(added_box_pair.reference)
    moved = apply_transform(added_box_pair.reference, rigid_transform(2.0, (0.2, -0.1, 0.05)))
    result = compare(reference, PointCloud.from_array(moved), method=method, variant=variant)
    assert not result.changed, result.calibration
    assert result.registration.fitness > 0.9
    assert result.regions == []


@pytest.mark.parametrize("method", METHODS)
def test_added_box_is_changed_with_a_region_at_the_right_place(method, added_box_pair):
    pair = added_box_pair
    result = compare(
        PointCloud.from_array(pair.reference, sensor_origin=pair.reference_origin),
        PointCloud.from_array(pair.scan, sensor_origin=pair.scan_origin),
        method=method,
    )
    assert result.changed, (result.score, result.threshold)
    true_added = apply_transform(pair.scan[pair.scan_changed], pair.true_transform)
    true_centre = true_added.mean(axis=0)
    added_regions = [region for region in result.regions if region.kind == "added"]
    assert added_regions
    assert any(
        np.all(np.asarray(region.bbox_min) - 0.05 <= true_centre)
        and np.all(true_centre <= np.asarray(region.bbox_max) + 0.05)
        for region in added_regions
    )


def test_unchanged_rescan_with_pose_error_is_not_changed(unchanged_pair):
    pair = unchanged_pair
    result = compare(
        PointCloud.from_array(pair.reference, sensor_origin=pair.reference_origin),
        PointCloud.from_array(pair.scan, sensor_origin=pair.scan_origin),
    )
    assert not result.changed, (result.score, result.threshold)
    assert result.regions == []


def test_params_of_a_result_replay_it_exactly(added_box_pair):
    pair = added_box_pair
    reference = PointCloud.from_array(pair.reference)
    scan = PointCloud.from_array(pair.scan)
    first = compare(reference, scan, method="gmm", random_state=7)
    replay = compare(reference, scan, method="gmm", params=first.params)
    assert replay.score == first.score
    assert replay.threshold == first.threshold
    np.testing.assert_array_equal(replay.scan_label, first.scan_label)


def test_georeferenced_coordinates_give_the_same_answer(added_box_pair):
    pair = added_box_pair
    offset = np.array([512_345.0, 5_412_345.0, 250.0])
    local = compare(PointCloud.from_array(pair.reference), PointCloud.from_array(pair.scan))
    far = compare(
        PointCloud.from_array(pair.reference + offset),
        PointCloud.from_array(pair.scan + offset),
    )
    assert far.changed == local.changed
    assert len(far.regions) == len(local.regions)
    np.testing.assert_allclose(
        np.asarray(far.regions[0].centroid) - offset, local.regions[0].centroid, atol=1e-3
    )
    np.testing.assert_array_equal(far.scan_label, local.scan_label)


def test_dropped_points_keep_their_place_in_labels(added_box_pair):
    points = added_box_pair.scan.copy()
    points[[0, 5, 17]] = np.nan
    scan = PointCloud.from_array(points)
    result = compare(PointCloud.from_array(added_box_pair.reference), scan)
    assert result.scan_label.shape == (len(points),)
    assert (result.scan_label[[0, 5, 17]] == -1).all()
    assert result.n_scan == len(points) - 3


def test_unknown_method_and_parameters_are_input_errors(added_box_pair):
    cloud = PointCloud.from_array(added_box_pair.reference)
    with pytest.raises(InputError, match="method"):
        compare(cloud, cloud, method="sift")
    with pytest.raises(InputError):
        compare(cloud, cloud, params={"no_such_parameter": 1})


def test_decision_rules(added_box_pair):
    pair = added_box_pair
    reference = PointCloud.from_array(pair.reference)
    scan = PointCloud.from_array(pair.scan)
    either = compare(reference, scan, method="pca", params={"decision": "either"})
    default = compare(reference, scan, method="pca")
    assert default.calibration.decision.rule == "regions"
    assert default.changed == (len(default.regions) > 0)
    detector_only = compare(reference, scan, method="pca", params={"decision": "detector"})
    decision = either.calibration.decision
    assert decision.rule == "either"
    assert either.changed == (decision.detector_changed or decision.n_regions > 0)
    assert detector_only.changed == (detector_only.score > detector_only.threshold)
    with pytest.raises(InputError, match="decision"):
        compare(reference, scan, params={"decision": "vote"})


def searches_running() -> list[str]:
    return [thread.name for thread in threading.enumerate() if "neighbourhood" in thread.name]


def test_the_reference_search_run_during_alignment_changes_nothing_and_ends_with_it(
    monkeypatch,
):
    """From REFERENCE_AHEAD_MIN_POINTS points (lowered here) and 2 threads the reference's
    neighbour search runs while the scan is aligned, and the scan's while its origin is
    resolved: the result is exactly the one-thread result."""
    started: list[int] = []

    class CountedSearch(neighbourhoods.NeighbourhoodSearch):
        def __init__(self, points, n_neighbors, openmp_threads=1, **options):
            started.append(len(points))
            super().__init__(points, n_neighbors, openmp_threads, **options)

    monkeypatch.setattr(neighbourhoods, "NeighbourhoodSearch", CountedSearch)
    # the threshold lowered for a smaller scene (what runs ahead does not depend on the size)
    monkeypatch.setattr(localise_stage, "REFERENCE_AHEAD_MIN_POINTS", SMALL_AHEAD_MIN_POINTS)
    pair = raycast_scene(
        n_points=SMALL_AHEAD_MIN_POINTS + 5_000,
        change="box",
        pose_error=(0.03, 0.4),
        random_state=5,
    )
    reference, scan = PointCloud.from_array(pair.reference), PointCloud.from_array(pair.scan)
    params = {
        "reference_origin": pair.reference_origin.tolist(),
        "scan_origin": pair.scan_origin.tolist(),
    }
    one = compare(reference, scan, params=params, threads=1)
    assert started == []
    two = compare(reference, scan, params=params, threads=2)
    assert started == [len(pair.reference), len(pair.scan)]
    assert searches_running() == []
    assert one.changed and one.regions
    assert two.score == one.score and two.registration == one.registration
    for name in ("reference_label", "scan_label", "reference_region", "scan_region"):
        np.testing.assert_array_equal(getattr(two, name), getattr(one, name))
    np.testing.assert_array_equal(two.reference_distance, one.reference_distance)
    assert two.localisation == one.localisation

    # an alignment that fails stops the search: no thread outlives the comparison
    far_away = PointCloud.from_array(pair.scan + np.array([500.0, 0.0, 0.0]))
    with pytest.raises(InputError, match="does not overlap"):
        compare(reference, far_away, threads=2)
    assert len(started) == 3  # the reference's only: the scan's starts once aligned
    assert searches_running() == []
    # no thread to be had for the search (as under a job's address-space cap): the reference
    # is searched in line instead
    start = threading.Thread.start

    def refuse(thread):
        if thread.name == "neighbourhood-search":
            raise RuntimeError("can't start new thread")
        start(thread)

    with monkeypatch.context() as refusing:
        refusing.setattr(threading.Thread, "start", refuse)
        without_thread = compare(reference, scan, params=params, threads=2)
    assert len(started) == 5  # both searches tried, neither started
    np.testing.assert_array_equal(without_thread.scan_label, one.scan_label)
    assert without_thread.score == one.score
    # bad localisation parameters are reported by localisation, as without the search
    with pytest.raises(InputError, match="n_neighbors"):
        compare(reference, scan, params={"localisation": {"n_neighbors": 2}}, threads=2)
    assert searches_running() == []


def test_the_detector_runs_after_the_localisation_on_the_calling_thread(
    monkeypatch, added_box_pair
):
    """With two threads the detection runs on the comparison's own thread once stage 4 has
    returned (s21 started it on a thread of its own beside the regions' clustering: +0.6-1.2
    CPU s and +30-40 MB of peak RSS on the held-out 1M pair, no quiet-wall gain), with the
    one-thread result."""
    from app.core import pipeline

    detected_on: list[str] = []
    localised: list[bool] = []
    localise_pair, detect_change = pipeline.localise_pair, pipeline.detect_change

    def localise(*args, **kwargs):
        result = localise_pair(*args, **kwargs)
        localised.append(True)
        return result

    def detect(*args, **kwargs):
        detected_on.append(threading.current_thread().name)
        assert localised, "the detection started before the localisation returned"
        return detect_change(*args, **kwargs)

    monkeypatch.setattr(pipeline, "localise_pair", localise)
    monkeypatch.setattr(pipeline, "detect_change", detect)
    reference = PointCloud.from_array(added_box_pair.reference)
    scan = PointCloud.from_array(added_box_pair.scan)
    params = {
        "reference_origin": added_box_pair.reference_origin.tolist(),
        "scan_origin": added_box_pair.scan_origin.tolist(),
    }
    two = compare(reference, scan, params=params, threads=2)
    assert detected_on == [threading.current_thread().name]
    one = compare(reference, scan, params=params, threads=1)
    assert two.score == one.score and two.threshold == one.threshold
    np.testing.assert_array_equal(two.scan_label, one.scan_label)


def test_the_detector_is_given_the_mutually_observed_rows_in_their_order() -> None:
    """detect_change hands the detector exactly the observed points of each cloud, in file
    order, as float64 rows (np.compress: the rows a boolean index takes)."""
    from types import SimpleNamespace

    from app.core.comparison.decide import detect_change
    from app.core.labels import LABEL_UNOBSERVED

    rng = np.random.default_rng(28)
    reference, scan = rng.normal(size=(3_000, 3)), rng.normal(size=(2_500, 3))
    labels = SimpleNamespace(
        reference_label=rng.choice(np.array([LABEL_UNOBSERVED, 0, 1], np.int8), 3_000),
        scan_label=rng.choice(np.array([LABEL_UNOBSERVED, 0, 1], np.int8), 2_500),
    )
    given: list[np.ndarray] = []

    class Recording:
        def detect(self, first: np.ndarray, second: np.ndarray) -> str:
            given.extend((first, second))
            return "detected"

    detected = detect_change(Recording(), reference, scan, labels)  # type: ignore[arg-type]
    assert detected.compared_points == "mutually observed"
    for points, label, got in zip(
        (reference, scan), (labels.reference_label, labels.scan_label), given, strict=True
    ):
        expected = points[label != LABEL_UNOBSERVED]
        assert got.dtype == np.float64 and got.flags.c_contiguous
        np.testing.assert_array_equal(got, expected)
