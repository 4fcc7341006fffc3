"""Several lidar stations per cloud: given, assigned, recovered; and the origin-free gap test.

Rules checked (measured numbers in bench/results/visibility.md, "Several stations per cloud"):

* one origin given as a list of one is the single-origin comparison, label for label;
* with every station's origin (and per-point station index) a merged survey's change is
  localised (IoU >= 0.9) and an unchanged one gives no region; "observed" means seen by any
  station of the other epoch, so more stations leave fewer points unobserved;
* origins without a station index: points are assigned to stations from their rings;
* stations are recovered from a merged cloud alone (to the millimetre where found), and a
  single-station cloud or a cloud without lidar structure is not taken for a survey;
* a dense point inside a hole of the other cloud's sampling (a blind disc) is no change
  without origins, while points off the other's surface or beyond its edge still are;
* bad origins and station indices are refused with a message that says what to fix.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
from pykdtree.kdtree import KDTree

from app.core.cloud import PointCloud
from app.core.datasets.lidar import LidarPair, lidar_directions, lidar_pair
from app.core.datasets.scenes import _transform_points, raycast_scene
from app.core.errors import InputError
from app.core.ground_truth import changed_iou
from app.core.labels import LABEL_CHANGED, LABEL_UNOBSERVED
from app.core.localise import EpochCloud, localise_changes
from app.core.localise.gaps import in_sampling_gap
from app.core.localise.rays import (
    STATUS_EDGE_ON,
    STATUS_SEEN_THROUGH,
    STATUS_SURFACE,
    STATUS_UNOBSERVED,
)
from app.core.localise.station_assignment import (
    RING_CONTRAST,
    assign_stations,
    grid_contrast,
    ring_contrast,
    station_contrasts,
)
from app.core.localise.surface import local_geometry
from app.core.localise.visibility import combine_station_status
from app.core.origins.station_recovery import recover_stations
from app.core.pipeline import compare, parse_comparison_params

STEP = 1.2  # degrees: ~25k points a station


@functools.cache
def survey(change: str, seed: int = 3, layout: str = "room") -> tuple[LidarPair, np.ndarray]:
    """A 3-station survey pair and its scan put back into the reference frame."""
    pair = lidar_pair(
        layout=layout,
        change=change,
        n_stations=3,
        angular_step_deg=STEP,
        misaligned=True,
        random_state=seed,
    )
    return pair, _transform_points(pair.scan, pair.true_transform)


def scan_origins(pair: LidarPair) -> np.ndarray:
    return _transform_points(pair.scan_origins, pair.true_transform)


def with_stations(pair: LidarPair, scan: np.ndarray, **options):
    return localise_changes(
        EpochCloud(pair.reference, origin=pair.reference_origins, station=pair.reference_station),
        EpochCloud(scan, origin=scan_origins(pair), station=pair.scan_station),
        **options,
    )


def test_one_origin_as_a_list_is_the_single_origin_comparison():
    pair = raycast_scene(n_points=20_000, change="mixed", pose_error=(0.03, 0.4), random_state=5)
    single = localise_changes(
        EpochCloud(pair.reference, origin=pair.reference_origin),
        EpochCloud(pair.aligned_scan(), origin=pair.aligned_scan_origin()),
    )
    listed = localise_changes(
        EpochCloud(pair.reference, origin=[pair.reference_origin.tolist()]),
        EpochCloud(
            pair.aligned_scan(),
            origin=pair.aligned_scan_origin()[None, :],
            station=np.zeros(len(pair.scan), dtype=np.int64),
        ),
    )
    assert np.array_equal(single.reference_label, listed.reference_label)
    assert np.array_equal(single.scan_label, listed.scan_label)
    assert len(single.regions) == len(listed.regions) > 0


@pytest.mark.parametrize("change", ["added", "mixed"])
def test_stations_given_localise_the_change(change):
    pair, scan = survey(change)
    localisation = with_stations(pair, scan)
    assert changed_iou(pair, localisation) >= 0.9
    assert localisation.parameters["reference_stations"] == 3
    assert localisation.parameters["scan_station_assignment"] == "given"


def test_stations_given_keep_an_unchanged_survey_quiet():
    pair, scan = survey("none")
    localisation = with_stations(pair, scan)
    assert localisation.regions == []
    assert not (localisation.reference_label == LABEL_CHANGED).any()


def test_observed_means_observed_by_any_station():
    pair, scan = survey("added")
    every = with_stations(pair, scan)
    # the same survey as if the reference had been taken by its first station alone
    first_only = pair.reference_station == 0
    alone = localise_changes(
        EpochCloud(pair.reference[first_only], origin=pair.reference_origins[0]),
        EpochCloud(scan, origin=scan_origins(pair), station=pair.scan_station),
    )
    assert np.count_nonzero(every.scan_label == LABEL_UNOBSERVED) < np.count_nonzero(
        alone.scan_label == LABEL_UNOBSERVED
    )
    # and what no reference station could see stays unobserved, never changed
    unseen = ~pair.scan_observed
    assert not (every.scan_label[unseen] == LABEL_CHANGED).any()


def test_assigned_stations_tie_to_the_first_and_off_ring_points_to_the_nearest():
    pair, _ = survey("added")
    origins = pair.reference_origins
    # the same station twice: every tie goes to the first of them, as an argmax does
    doubled = assign_stations(pair.reference, np.vstack([origins[:1], origins[:1]]))
    assert (doubled == 0).all()
    # the station with the largest contrast, else (on no station's rings) the nearest
    rng = np.random.default_rng(0)
    noise = rng.uniform(pair.reference.min(axis=0), pair.reference.max(axis=0), (20_000, 3))
    points = np.vstack([pair.reference[::20], noise])
    grids = station_contrasts(points, origins)
    contrast = np.stack(
        [grid_contrast(points, origin, grid) for origin, grid in zip(origins, grids, strict=True)]
    )
    squared = ((points[:, None, :] - origins[None, :, :]) ** 2).sum(axis=2)
    on_rings = contrast.max(axis=0) >= RING_CONTRAST
    assert 0 < np.count_nonzero(~on_rings) < len(points)
    expected = np.where(on_rings, contrast.argmax(axis=0), squared.argmin(axis=1))
    np.testing.assert_array_equal(assign_stations(points, origins), expected)


def test_origins_without_station_index_are_assigned_from_the_rings():
    pair, scan = survey("added")
    assigned = assign_stations(pair.reference, pair.reference_origins)
    assert np.mean(assigned == pair.reference_station) >= 0.95
    localisation = localise_changes(
        EpochCloud(pair.reference, origin=pair.reference_origins),
        EpochCloud(scan, origin=scan_origins(pair)),
    )
    assert localisation.parameters["reference_station_assignment"] == "assigned"
    assert changed_iou(pair, localisation) >= 0.9


def test_combined_status_is_any_station_that_saw():
    s, t, u, e = STATUS_SURFACE, STATUS_SEEN_THROUGH, STATUS_UNOBSERVED, STATUS_EDGE_ON
    statuses = np.array(
        [
            [u, t, u, s, t, e, u],
            [u, u, s, u, s, u, e],
            [u, u, u, u, t, u, u],
        ],
        dtype=np.int8,
    )
    assert combine_station_status(statuses).tolist() == [u, t, s, s, t, e, e]
    assert combine_station_status(statuses[:1]).tolist() == statuses[0].tolist()


def test_stations_are_recovered_from_a_merged_warehouse_survey():
    pair, _ = survey("added", seed=0, layout="warehouse")
    found = recover_stations(pair.reference)
    assert found.several
    error = np.linalg.norm(found.origins[:, None, :] - pair.reference_origins[None], axis=2)
    assert (error.min(axis=1) <= 0.01).all()  # every station found is a true one


def test_a_single_station_or_a_structureless_cloud_is_not_a_survey():
    single = lidar_pair(layout="room", change="none", angular_step_deg=0.8, random_state=1)
    assert not recover_stations(single.reference).several
    random_points = np.random.default_rng(0).uniform(0.0, 10.0, size=(40_000, 3))
    assert recover_stations(random_points).origins.shape[0] == 0


def test_a_hole_in_the_other_clouds_sampling_is_not_a_change():
    # the other cloud: a floor sampled every 5 cm with a blind disc of 1 m radius cut out
    grid = np.arange(-4.0, 4.0, 0.05)
    floor = np.stack(np.meshgrid(grid, grid, indexing="ij"), -1).reshape(-1, 2)
    floor = floor[np.hypot(floor[:, 0] - 0.5, floor[:, 1]) > 1.0]
    other = local_geometry(np.column_stack([floor, np.zeros(len(floor))]), 10)
    candidates = np.array(
        [
            [0.5, 0.0, 0.0],  # the disc's centre
            [1.2, 0.3, 0.0],  # off centre, still inside
            [0.5, 0.0, 0.6],  # 0.6 m above the floor: a box top
            [4.6, 0.0, 0.0],  # beyond the floor's edge: a shadow's rim
        ]
    )
    nearest, _ = KDTree(other.points).query(candidates, k=1)
    up = np.tile([0.0, 0.0, 1.0], (len(candidates), 1))
    gap = in_sampling_gap(candidates, up, nearest, other=other, tolerance=0.05)
    assert gap.tolist() == [True, True, False, False]


def test_compare_takes_station_lists_and_the_station_index_attribute():
    pair, _ = survey("added")
    reference = PointCloud.from_array(
        pair.reference, attributes={"station_index": pair.reference_station}
    )
    scan = PointCloud.from_array(pair.scan, attributes={"station_index": pair.scan_station})
    result = compare(
        reference,
        scan,
        method="gmm",
        variant="improved",
        params={
            "reference_origin": pair.reference_origins.tolist(),
            "scan_origin": pair.scan_origins.tolist(),
        },
    )
    assert result.localisation["reference_station_assignment"] == "given"
    assert result.localisation["scan_stations"] == 3
    assert result.params["scan_origin"] == pair.scan_origins.tolist()
    assert changed_iou(pair, result) >= 0.9


@pytest.mark.parametrize(
    ("origin", "message"),
    [
        ([0.0, 1.0], "3 finite numbers"),
        ([[0.0, 1.0, 2.0], [1.0, 2.0]], "3 finite numbers"),
        ([[0.0, 1.0, 2.0], [1.0, np.nan, 2.0]], "station 1's origin"),
        ("here", "3 finite numbers"),
        ([], "3 finite numbers"),
    ],
)
def test_bad_origins_are_refused_with_what_to_fix(origin, message):
    points = np.random.default_rng(0).normal(size=(50, 3))
    with pytest.raises(InputError, match=message):
        localise_changes(EpochCloud(points, origin=origin), points)
    with pytest.raises(InputError, match=message):
        parse_comparison_params("gmm", "improved", {"scan_origin": origin})


@pytest.mark.parametrize(
    ("station", "message"),
    [
        (np.zeros(49, dtype=np.int64), "one station index per point"),
        (np.full(50, 2), r"0\.\.1"),
        (np.full(50, -1), r"0\.\.1"),
        (np.full(50, 0.5), "whole numbers"),
        (np.array(["a"] * 50), "integer station indices"),
    ],
)
def test_bad_station_indices_are_refused_with_what_to_fix(station, message):
    points = np.random.default_rng(0).normal(size=(50, 3))
    origins = [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]
    with pytest.raises(InputError, match=message):
        localise_changes(points, EpochCloud(points, origin=origins, station=station))


def test_a_station_index_needs_the_stations_origins():
    points = np.random.default_rng(0).normal(size=(50, 3))
    with pytest.raises(InputError, match="needs the stations' origins"):
        localise_changes(points, EpochCloud(points, station=np.zeros(50, dtype=np.int64)))
    cloud = PointCloud.from_array(points, attributes={"station_index": np.full(50, 3)})
    with pytest.raises(InputError, match=r"station_index must lie in 0\.\.1"):
        compare(
            cloud,
            cloud,
            method="gmm",
            variant="improved",
            align=False,
            params={"reference_origin": [[0, 0, 0], [1, 1, 1]]},
        )


def test_station_assignment_does_not_depend_on_its_chunks_and_takes_float32(monkeypatch) -> None:
    pair, _ = survey("added")
    whole = assign_stations(pair.reference, pair.reference_origins)
    monkeypatch.setattr("app.core.localise.station_assignment.ASSIGN_CHUNK", 997)
    chunked = assign_stations(pair.reference, pair.reference_origins, np.int8)
    assert chunked.dtype == np.int8
    assert np.array_equal(chunked, whole)
    right = np.mean(whole == pair.reference_station)
    assert right > 0.9  # the test can tell stations apart
    # float32 moves points by micrometres: a few move across a 0.01 degree elevation bin
    lean = assign_stations(pair.reference.astype(np.float32), pair.reference_origins)
    assert np.mean(lean == pair.reference_station) > right - 0.01


def _hall_survey(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A hall's inside scanned from 3 stations at one height on 1 degree grids (each turned at
    random), the origins known only to a few millimetres: points, origins, true stations."""
    rng = np.random.default_rng(seed)
    high = np.array([40.0, 12.0, 6.0])
    height = rng.uniform(1.2, 1.7)
    x = (np.arange(3) + rng.uniform(0.2, 0.8, 3)) * high[0] / 3
    origins = np.column_stack([x, rng.uniform(2.0, 10.0, 3), np.full(3, height)])
    points, station = [], []
    for number, origin in enumerate(origins):
        direction = lidar_directions(1.0, 1.0, rng.uniform(0.0, 360.0))
        with np.errstate(divide="ignore"):
            reach = np.where(direction > 0, (high - origin) / direction, -origin / direction)
        reach = np.where(direction == 0, np.inf, reach).min(axis=1)
        reach *= 1.0 + rng.normal(0.0, 0.002, reach.shape)
        points.append(origin + direction * reach[:, None])
        station.append(np.full(reach.shape, number))
    estimated = origins + rng.normal(0.0, 0.003, origins.shape)
    return np.vstack(points), estimated, np.concatenate(station)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_scanners_columns_tell_its_returns_from_another_stations_rings(seed):
    # issue 29, TLS 2004: stations at one height share ring elevations, and origins known to a
    # few millimetres blur the rings of near returns; a terrestrial scanner's returns also lie
    # on its columns (fixed azimuth steps), which another station's rings do not line up with
    points, origins, station = _hall_survey(seed)
    contrast = np.stack([ring_contrast(points, origin) for origin in origins])
    squared = ((points[:, None, :] - origins[None, :, :]) ** 2).sum(axis=2)
    by_rings = np.where(
        contrast.max(axis=0) >= RING_CONTRAST, contrast.argmax(axis=0), squared.argmin(axis=1)
    )
    wrong_by_rings = np.count_nonzero(by_rings != station)
    assert wrong_by_rings > 0  # the case is there
    wrong = np.count_nonzero(assign_stations(points, origins) != station)
    assert wrong <= 0.75 * wrong_by_rings
