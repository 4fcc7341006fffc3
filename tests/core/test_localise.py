"""Change localisation on the paper's corridor and on ray-cast lidar rescans.

Rules checked (the measured numbers are in docs/localisation.md):

* unchanged rescans (moved sensor, occlusions, 3 cm / 0.4 degree pose error, aligned with the
  true transform) give no region at all (clusters below the default ``min_region_points``,
  max(4, 0.08 sqrt(n)) = 18 at 50k points, are noise by definition) and < 0.5 % of the points
  falsely changed;
* changed rescans give IoU >= 0.85 of the changed points (over points the ground truth marks
  observed) and a region of the right kind whose box contains each changed object's centre;
* the visibility test labels unobserved what the other sensor could not see (agreement with
  the exact ray-cast ground truth >= 95 %), and never calls such a point changed.
"""

from __future__ import annotations

import functools
import json
import time
from typing import Any

import numpy as np
import pytest

from app.core.datasets.scenes import (
    SyntheticPair,
    paper_corridor,
    raycast_scene,
    raycast_scene_objects,
)
from app.core.errors import InputError, PointCloudError
from app.core.ground_truth import changed_iou
from app.core.labels import LABEL_CHANGED, LABEL_UNOBSERVED
from app.core.localise import (
    DEFAULT_PARAMETERS,
    EpochCloud,
    Localisation,
    NeighbourhoodSearch,
    localise_changes,
    nearest_neighbourhoods,
    neighbourhood_size,
)
from app.core.localise import rays as rays_module
from app.core.localise import surface as surface_module

SCENE_POINTS = 50_000
POSE_ERROR = (0.03, 0.4)  # metres, degrees


@functools.cache
def localised_scene(
    change: str, seed: int = 11, n_points: int = SCENE_POINTS
) -> tuple[SyntheticPair, Localisation]:
    """A ray-cast rescan, aligned with the true transform, localised with both origins."""
    pair = raycast_scene(n_points=n_points, change=change, pose_error=POSE_ERROR, random_state=seed)
    return pair, localise_pair(pair)


def localise_pair(
    pair: SyntheticPair, reference_neighbourhoods: Any = None, **options: Any
) -> Localisation:
    """``localise_changes`` on a pair aligned with its true transform, with both origins."""
    return localise_changes(
        EpochCloud(
            pair.reference, origin=pair.reference_origin, neighbourhoods=reference_neighbourhoods
        ),
        EpochCloud(pair.aligned_scan(), origin=pair.aligned_scan_origin()),
        **options,
    )


def false_changed_fraction(pair: SyntheticPair, localisation: Localisation) -> float:
    false = np.count_nonzero(
        (localisation.reference_label == LABEL_CHANGED) & ~pair.reference_changed
    ) + np.count_nonzero((localisation.scan_label == LABEL_CHANGED) & ~pair.scan_changed)
    return false / (len(pair.reference) + len(pair.scan))


def visibility_agreement(label: np.ndarray, observed: np.ndarray) -> float:
    return float(np.mean((label == LABEL_UNOBSERVED) == ~observed))


def region_containing(localisation: Localisation, kind: str, point: np.ndarray):
    for region in localisation.regions:
        if (
            region.kind == kind
            and np.all(region.bbox_min <= point)
            and np.all(point <= region.bbox_max)
        ):
            return region
    return None


# --- ray-cast rescans ---------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [11, 12])
def test_unchanged_rescan_has_no_real_region_and_few_false_changes(seed):
    pair, localisation = localised_scene("none", seed)
    assert localisation.parameters["min_region_points"] == 18  # 0.08 sqrt(50k)
    assert [region.n_points for region in localisation.regions] == []
    assert false_changed_fraction(pair, localisation) < 0.005


@pytest.mark.parametrize("change", ["box", "removed", "moved"])
def test_changed_rescan_localises_the_object(change):
    pair, localisation = localised_scene(change)
    assert changed_iou(pair, localisation) >= 0.85
    reference_only, scan_only = raycast_scene_objects(change)
    for kind, boxes in (("removed", reference_only), ("added", scan_only)):
        for box in boxes:
            region = region_containing(localisation, kind, box.centre)
            assert region is not None, f"no {kind} region contains {box.name}'s centre"
            assert region.n_points > 100
    assert false_changed_fraction(pair, localisation) < 0.005


@pytest.mark.parametrize("change", ["none", "box", "removed"])
def test_visibility_test_labels_what_the_other_sensor_missed_unobserved(change):
    pair, localisation = localised_scene(change)
    assert (~pair.reference_observed).mean() > 0.05  # there are occlusions to find
    assert visibility_agreement(localisation.reference_label, pair.reference_observed) >= 0.95
    assert visibility_agreement(localisation.scan_label, pair.scan_observed) >= 0.95
    # most points the scan could not see are labelled so, and (almost) none is called changed
    occluded = ~pair.reference_observed
    assert np.mean(localisation.reference_label[occluded] == LABEL_UNOBSERVED) > 0.8
    assert np.count_nonzero(localisation.reference_label[occluded] == LABEL_CHANGED) <= (
        1e-3 * occluded.sum()
    )


def test_labels_regions_and_distances_are_consistent():
    pair, localisation = localised_scene("moved")
    n, m = len(pair.reference), len(pair.scan)
    assert localisation.reference_label.shape == (n,) and localisation.scan_label.shape == (m,)
    assert localisation.reference_label.dtype == np.int8
    assert localisation.reference_distance.dtype == np.float32
    assert localisation.reference_region.dtype == np.int32
    sizes = [region.n_points for region in localisation.regions]
    assert sizes == sorted(sizes, reverse=True)
    for label, distance, region_index, kind, points in (
        (
            localisation.reference_label,
            localisation.reference_distance,
            localisation.reference_region,
            "removed",
            pair.reference,
        ),
        (
            localisation.scan_label,
            localisation.scan_distance,
            localisation.scan_region,
            "added",
            pair.aligned_scan(),
        ),
    ):
        assert set(np.unique(label)) <= {-1, 0, 1}
        np.testing.assert_array_equal(np.isnan(distance), label == LABEL_UNOBSERVED)
        np.testing.assert_array_equal(region_index >= 0, label == LABEL_CHANGED)
        for number, region in enumerate(localisation.regions):
            if region.kind != kind:
                assert not np.any(region_index == number)
                continue
            members = np.flatnonzero(region_index == number)
            np.testing.assert_array_equal(region.point_indices, members)
            assert region.point_indices.dtype == np.int64
            region_points = points[members]
            np.testing.assert_allclose(region.centroid, region_points.mean(axis=0))
            np.testing.assert_allclose(region.bbox_min, region_points.min(axis=0))
            np.testing.assert_allclose(region.bbox_max, region_points.max(axis=0))
            assert region.max_distance == pytest.approx(float(distance[members].max()), rel=1e-5)
            assert region.mean_distance > localisation.parameters["threshold"]


def test_parameters_are_json_and_replay_the_result():
    pair, localisation = localised_scene("box")
    parameters = json.loads(json.dumps(localisation.parameters))
    assert parameters["reference_visibility"] == parameters["scan_visibility"] == "ray"
    assert 0.004 < parameters["reference_noise"] < 0.012  # 1 cm along rays, less along normals
    replay_params = {name: parameters[name] for name in DEFAULT_PARAMETERS}
    replayed = localise_pair(
        pair, min_region_points=parameters["min_region_points"], **replay_params
    )
    np.testing.assert_array_equal(replayed.reference_label, localisation.reference_label)
    np.testing.assert_array_equal(replayed.scan_label, localisation.scan_label)


@pytest.mark.parametrize("threads", [1, 2])
def test_the_result_does_not_depend_on_the_thread_count(threads):
    pair, localisation = localised_scene("removed")
    other = localise_pair(pair, threads=threads)
    for name in ("reference_label", "scan_label", "reference_region", "scan_region"):
        np.testing.assert_array_equal(getattr(other, name), getattr(localisation, name))
    np.testing.assert_array_equal(other.reference_distance, localisation.reference_distance)
    assert other.parameters == localisation.parameters
    assert len(other.regions) == len(localisation.regions) > 0


def test_chunks_worked_on_two_threads_give_the_same_result(monkeypatch):
    # chunks far smaller than the scene, so that the plane fits, spacings and ray tests run
    # many chunks on both threads at once
    pair, localisation = localised_scene("removed")
    monkeypatch.setattr(surface_module, "CHUNK", 97)
    monkeypatch.setattr(rays_module, "GATHER_CHUNK", 13)
    one, two = (localise_pair(pair, threads=threads) for threads in (1, 2))
    assert_same_localisation(two, one)
    assert_same_localisation(one, localisation)
    assert one.parameters["scan_candidates"] > 13 * 4


def assert_same_localisation(first: Localisation, second: Localisation) -> None:
    for name in ("reference_label", "scan_label", "reference_region", "scan_region"):
        np.testing.assert_array_equal(getattr(first, name), getattr(second, name))
    np.testing.assert_array_equal(first.reference_distance, second.reference_distance)
    np.testing.assert_array_equal(first.scan_distance, second.scan_distance)
    assert first.parameters == second.parameters


@pytest.mark.parametrize("threads", [1, 2])
def test_reference_neighbourhoods_found_ahead_give_the_same_result(threads):
    pair, localisation = localised_scene("removed")
    reference = np.ascontiguousarray(pair.reference)
    k = neighbourhood_size(len(reference))
    assert k == DEFAULT_PARAMETERS["n_neighbors"]
    search = NeighbourhoodSearch(reference, k, openmp_threads=1)
    assert_same_localisation(
        localise_pair(pair, threads=threads, reference_neighbourhoods=search), localisation
    )
    # a finished search as a plain value, used twice: the localiser leaves it as it was
    neighbourhoods = nearest_neighbourhoods(reference, k)
    kth_distance = neighbourhoods.kth_distance.copy()
    for _ in range(2):
        assert_same_localisation(
            localise_pair(pair, threads=threads, reference_neighbourhoods=neighbourhoods),
            localisation,
        )
    np.testing.assert_array_equal(neighbourhoods.kth_distance, kth_distance)
    assert neighbourhoods.neighbor_index.shape == (len(reference), k + 1)


def test_neighbourhood_search_hands_its_result_over_once_and_stops_when_cancelled():
    pair, _ = localised_scene("removed")
    reference = np.ascontiguousarray(pair.reference)
    search = NeighbourhoodSearch(reference, 10)
    taken = search.take()
    expected = nearest_neighbourhoods(reference, 10)
    np.testing.assert_array_equal(taken.neighbor_index, expected.neighbor_index)
    np.testing.assert_array_equal(taken.kth_distance, expected.kth_distance)
    assert taken.neighbor_index[:, 0].tolist() == list(range(len(reference)))  # itself first
    with pytest.raises(RuntimeError, match="cancelled or already taken"):
        search.take()
    cancelled = NeighbourhoodSearch(reference, 10)
    cancelled.cancel()
    assert not cancelled._thread.is_alive()
    with pytest.raises(RuntimeError, match="cancelled or already taken"):
        cancelled.take()
    with pytest.raises(ValueError, match=r"n_neighbors must be in 1\.\."):
        nearest_neighbourhoods(reference[:5], 5)


def test_neighbourhoods_of_another_cloud_or_size_are_refused():
    pair, _ = localised_scene("removed")
    other_k = nearest_neighbourhoods(np.ascontiguousarray(pair.reference), 7)
    with pytest.raises(ValueError, match="another cloud or k"):
        localise_pair(pair, reference_neighbourhoods=other_k)
    other_cloud = nearest_neighbourhoods(np.ascontiguousarray(pair.reference[:-1]), 10)
    with pytest.raises(ValueError, match="another cloud or k"):
        localise_pair(pair, reference_neighbourhoods=other_cloud)
    with pytest.raises(InputError, match="n_neighbors"):
        neighbourhood_size(100, n_neighbors=2)


def test_registration_rmse_widens_the_threshold():
    pair, localisation = localised_scene("box")
    wider = localise_pair(pair, registration_rmse=0.05)
    assert wider.parameters["threshold"] > localisation.parameters["threshold"] + 0.1
    assert wider.parameters["n_scan_changed"] <= localisation.parameters["n_scan_changed"]
    box = raycast_scene_objects("box")[1][0]
    assert region_containing(wider, "added", box.centre) is not None


def test_min_region_points_drops_small_clusters():
    pair = raycast_scene(n_points=10_000, change="box", random_state=2)
    reference = EpochCloud(pair.reference, origin=pair.reference_origin)
    scan = EpochCloud(pair.aligned_scan(), origin=pair.aligned_scan_origin())
    default = localise_changes(reference, scan)
    assert default.parameters["min_region_points"] == 8  # max(4, 0.08 sqrt(10k))
    assert default.regions
    strict = localise_changes(reference, scan, min_region_points=100_000)
    assert strict.regions == []
    assert not np.any(strict.scan_label == LABEL_CHANGED)
    assert not np.any(strict.reference_label == LABEL_CHANGED)


# --- the paper's corridor ----------------------------------------------------------------------


@pytest.mark.parametrize("change_fraction", [0.1, 0.33])
@pytest.mark.parametrize("noise_variance", [1e-5, 1e-4, 1e-3])
def test_corridor_box_is_localised(noise_variance, change_fraction):
    box_front_centre = np.array([-0.5, 0.0, 1.0])
    ious = []
    for seed in range(10):
        pair = paper_corridor(
            noise_variance=noise_variance, change_fraction=change_fraction, random_state=seed
        )
        localisation = localise_changes(pair.reference, pair.scan)
        assert localisation.parameters["reference_visibility"] == "maps"
        ious.append(changed_iou(pair, localisation))
        assert region_containing(localisation, "added", box_front_centre) is not None
    assert np.mean(ious) >= 0.85
    assert np.min(ious) >= 0.75


def test_corridor_without_change_has_no_change():
    for seed in range(10):
        pair = paper_corridor(noise_variance=1e-3, random_state=seed)
        localisation = localise_changes(pair.reference, pair.scan)
        assert localisation.regions == []
        assert not np.any(localisation.reference_label == LABEL_CHANGED)


def test_noise_is_estimated_from_plane_fit_residuals():
    pair = paper_corridor(n_points=3000, noise_variance=1e-4, random_state=0)
    parameters = localise_changes(pair.reference, pair.scan).parameters
    assert parameters["reference_noise"] == pytest.approx(0.01, rel=0.3)
    assert parameters["scan_noise"] == pytest.approx(0.01, rel=0.3)


# --- input validation --------------------------------------------------------------------------


def test_invalid_input_is_rejected_with_a_reason():
    points = np.random.default_rng(0).normal(size=(50, 3))
    with pytest.raises(PointCloudError, match=r"shape \(n, 3\)"):
        localise_changes(points[:, :2], points)
    with pytest.raises(PointCloudError, match="at least"):
        localise_changes(points[:5], points)
    bad = points.copy()
    bad[3, 1] = np.nan
    with pytest.raises(PointCloudError, match="NaN"):
        localise_changes(points, bad)
    with pytest.raises(InputError, match="unknown localisation parameter"):
        localise_changes(points, points, neighbours=5)
    with pytest.raises(InputError, match="threshold_factor"):
        localise_changes(points, points, threshold_factor=-1)
    with pytest.raises(InputError, match="n_neighbors"):
        localise_changes(points, points, n_neighbors=2)
    with pytest.raises(InputError, match="scan_origin"):
        localise_changes(points, EpochCloud(points, origin=[0, 0]))
    with pytest.raises(InputError, match="registration_rmse"):
        localise_changes(points, points, registration_rmse=-0.1)


def test_identical_clouds_have_no_change():
    pair = raycast_scene(n_points=5000, change="none", random_state=0)
    localisation = localise_changes(
        EpochCloud(pair.reference, origin=pair.reference_origin),
        EpochCloud(pair.reference, origin=pair.reference_origin),
    )
    assert not np.any(localisation.reference_label)
    assert not np.any(localisation.scan_label)
    assert localisation.regions == []


# --- full size ----------------------------------------------------------------------------------


@pytest.mark.slow
def test_full_size_rescans_accuracy():
    """200k x 200k pairs of every kind; prints the table quoted in docs/localisation.md."""
    rows = []
    for change in ("none", "box", "removed", "moved", "mixed"):
        pair = raycast_scene(
            n_points=200_000, change=change, pose_error=POSE_ERROR, random_state=21
        )
        started = time.process_time()
        localisation = localise_changes(
            EpochCloud(pair.reference, origin=pair.reference_origin),
            EpochCloud(pair.aligned_scan(), origin=pair.aligned_scan_origin()),
        )
        cpu_seconds = time.process_time() - started
        iou = changed_iou(pair, localisation)
        false_fraction = false_changed_fraction(pair, localisation)
        agreement = visibility_agreement(localisation.reference_label, pair.reference_observed)
        rows.append(
            (change, iou, false_fraction, agreement, len(localisation.regions), cpu_seconds)
        )
        assert false_fraction < 0.005
        assert agreement >= 0.95
        if change == "none":
            assert localisation.regions == []
        else:
            assert iou >= 0.85
    print("\nchange   IoU    false%  agreement  regions  cpu_s")
    for change, iou, false_fraction, agreement, n_regions, cpu_seconds in rows:
        iou_cell = "  -  " if change == "none" else f"{iou:.3f}"
        print(
            f"{change:8s} {iou_cell}  {100 * false_fraction:.3f}   {agreement:.3f}      "
            f"{n_regions:3d}    {cpu_seconds:.2f}"
        )


# --- benchmark: `OMP_NUM_THREADS=1 .venv/bin/python -m tests.core.test_localise [n] [seeds]` ----


def benchmark(n_points: int = SCENE_POINTS, n_seeds: int = 8) -> None:
    """Print the accuracy and speed tables of docs/localisation.md (Markdown)."""
    print(f"ray-cast rescans: {n_points} points, pose error {POSE_ERROR}, {n_seeds} seeds\n")
    print(
        "| change | IoU mean | IoU min | false % mean | false % max | largest spurious region "
        "(without minimum size) | visibility agreement ref / scan (min) | CPU s |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for change in ("none", "box", "removed", "moved", "mixed"):
        ious, falses, spurious, agree_reference, agree_scan, cpu = [], [], [], [], [], []
        for seed in range(100, 100 + n_seeds):
            pair = raycast_scene(
                n_points=n_points, change=change, pose_error=POSE_ERROR, random_state=seed
            )
            started = time.process_time()
            localisation = localise_changes(
                EpochCloud(pair.reference, origin=pair.reference_origin),
                EpochCloud(pair.aligned_scan(), origin=pair.aligned_scan_origin()),
            )
            cpu.append(time.process_time() - started)
            if change != "none":
                ious.append(changed_iou(pair, localisation))
            falses.append(100 * false_changed_fraction(pair, localisation))
            truth = {"removed": pair.reference_changed, "added": pair.scan_changed}
            unfiltered = localise_changes(
                EpochCloud(pair.reference, origin=pair.reference_origin),
                EpochCloud(pair.aligned_scan(), origin=pair.aligned_scan_origin()),
                min_region_points=1,
            )
            spurious.append(
                [
                    max(
                        (
                            region.n_points
                            for region in result.regions
                            if truth[region.kind][region.point_indices].mean() < 0.5
                        ),
                        default=0,
                    )
                    for result in (localisation, unfiltered)
                ]
            )
            agree_reference.append(
                visibility_agreement(localisation.reference_label, pair.reference_observed)
            )
            agree_scan.append(visibility_agreement(localisation.scan_label, pair.scan_observed))
        iou_cells = f"{np.mean(ious):.3f} | {np.min(ious):.3f}" if ious else "- | -"
        print(
            f"| {change} | {iou_cells} | {np.mean(falses):.3f} | {np.max(falses):.3f} "
            f"| {max(kept for kept, _ in spurious)} ({max(raw for _, raw in spurious)}) "
            f"| {np.min(agree_reference):.3f} / {np.min(agree_scan):.3f} "
            f"| {np.mean(cpu):.2f} |"
        )
    fractions = (0.03, 0.1, 0.2, 0.33)
    print("\npaper corridor (300 points, no origins): IoU mean / min over 10 seeds\n")
    print("| noise variance | " + " | ".join(f"{f:.0%} moved" for f in fractions) + " |")
    print("|---|" + "---|" * len(fractions))
    for noise_variance in (1e-5, 1e-4, 1e-3, 1e-2):
        cells = []
        for change_fraction in fractions:
            values = []
            for seed in range(10):
                pair = paper_corridor(
                    noise_variance=noise_variance,
                    change_fraction=change_fraction,
                    random_state=seed,
                )
                values.append(changed_iou(pair, localise_changes(pair.reference, pair.scan)))
            cells.append(f"{np.mean(values):.2f} / {np.min(values):.2f}")
        print(f"| {noise_variance:g} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    import sys

    benchmark(*(int(argument) for argument in sys.argv[1:3]))
