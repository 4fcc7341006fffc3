"""E57 files (several scans with poses) and per-point station fields of PLY/LAS.

Rules checked:

* an E57 file's scans come out in the file's frame (each scan's pose applied), with a
  ``station_index`` per point and each scan's origin (its pose's translation) as the cloud's
  sensor origins; one scan gives one origin; the summary an upload gets agrees with the cloud;
* truncated, empty, scan-less and not-E57 content is refused with libE57Format's reason;
* per-point fields ``station``/``scan_index``/``station_index`` become the station index, and
  ``origin_x/y/z`` the station origins (numbered in the file's order), in PLY and LAS;
  malformed ones are refused with a message that says what to fix;
* compare() uses the stations a file carries: a merged survey written as E57 is localised as
  well as with the stations given by hand.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest

from app.core.datasets.lidar import LidarPair, lidar_pair
from app.core.errors import InputError, PointCloudError
from app.core.formats import detect_format, read_point_cloud, summarise_point_cloud
from app.core.ground_truth import changed_iou
from app.core.origins.known_stations import estimate_each_station
from app.core.pipeline import compare
from app.testing.files import e57_bytes, las_bytes, ply_bytes
from app.testing.scenes import random_points
from tests.helpers.clouds import assert_summary_of


def yaw_tilt_quaternion(yaw: float, tilt: float) -> np.ndarray:
    """A unit quaternion (w, x, y, z): a turn about z by ``yaw`` after one about x by ``tilt``."""
    about_z = np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])
    about_x = np.array([np.cos(tilt / 2), np.sin(tilt / 2), 0.0, 0.0])
    w1, x1, y1, z1 = about_z
    w2, x2, y2, z2 = about_x
    return np.array(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ]
    )


def rotation_of(quaternion: np.ndarray) -> np.ndarray:
    """The 3x3 rotation matrix of a unit quaternion (w, x, y, z)."""
    w, x, y, z = quaternion
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def stations_as_e57(points: np.ndarray, station: np.ndarray, origins: np.ndarray, seed: int):
    """E57 bytes holding each station's points in its own frame, posed with a random yaw/tilt."""
    rng = np.random.default_rng(seed)
    scans, poses = [], []
    for index, origin in enumerate(origins):
        quaternion = yaw_tilt_quaternion(rng.uniform(-np.pi, np.pi), rng.uniform(-0.05, 0.05))
        world = points[station == index]
        scans.append((world - origin) @ rotation_of(quaternion))  # R^T (p - t), row-wise
        poses.append((quaternion, origin))
    return e57_bytes(scans, poses)


def test_several_scans_come_out_in_the_file_frame_with_station_index_and_origins():
    rng = np.random.default_rng(5)
    origins = np.array([[10.0, 20.0, 1.2], [14.0, 21.0, 1.4], [11.0, 26.0, 0.9]])
    station = np.repeat([0, 1, 2], [300, 200, 250])
    world = origins[station] + rng.uniform(-5, 5, size=(len(station), 3))
    content = stations_as_e57(world, station, origins, seed=1)
    assert detect_format(None, content[:4096]) == "e57"

    cloud = read_point_cloud(content, filename="survey.e57")

    np.testing.assert_allclose(cloud.points, world, atol=1e-5)  # stored as float32
    np.testing.assert_array_equal(cloud.attributes["station_index"], station)
    np.testing.assert_allclose(cloud.sensor_origin, origins)
    summary = summarise_point_cloud(content, filename="survey.e57")
    assert_summary_of(summary, cloud)
    assert summary.n_stations == 3
    np.testing.assert_allclose(summary.sensor_origin, origins)


def test_one_scan_gives_one_origin_and_intensity_is_kept(tmp_path):
    points = random_points(100, seed=2)
    path = tmp_path / "one.e57"
    path.write_bytes(e57_bytes([points], [((1, 0, 0, 0), (3.0, -2.0, 1.5))], intensity=True))

    cloud = read_point_cloud(path)

    np.testing.assert_allclose(cloud.points, points + np.array([3.0, -2.0, 1.5]))
    assert cloud.sensor_origin.tolist() == [3.0, -2.0, 1.5]
    assert cloud.attributes["intensity"].tolist() == list(range(100))


def test_points_flagged_invalid_are_left_out():
    points = random_points(50, seed=3)
    some_invalid = np.arange(50) % 5 == 0
    content = e57_bytes(
        [points, points],
        [((1, 0, 0, 0), (0, 0, 0)), ((1, 0, 0, 0), (9, 0, 1))],
        invalid=[some_invalid, None],
    )

    cloud = read_point_cloud(content, filename="gappy.e57")

    assert cloud.sensor_origin.tolist() == [[0, 0, 0], [9, 0, 1]]
    assert np.bincount(cloud.attributes["station_index"]).tolist() == [40, 50]
    np.testing.assert_allclose(cloud.points[:40], points[~some_invalid], atol=1e-5)


@functools.cache
def e57_content() -> bytes:
    return e57_bytes([random_points(400, seed=4)] * 2, [((1, 0, 0, 0), (0, 0, 0))] * 2)


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: e57_content()[: len(e57_content()) // 2], "ErrorBadFileLength"),
        (lambda: e57_content()[:100], "unreadable E57 file"),
        (lambda: e57_content()[:-10], "size in file header not same as actual"),
        (lambda: b"ASTM-E57" + bytes(2000), "unreadable E57 file"),
        (lambda: e57_bytes([]), "holds no scan"),
        (lambda: b"this is not an e57 file at all\n" * 10, "not an E57 file"),
    ],
    ids=["half", "100-bytes", "short-by-10", "zero-pages", "no-scan", "text"],
)
def test_bad_e57_content_is_refused_with_the_reader_reason(make, message):
    content = make()
    with pytest.raises(PointCloudError, match=message) as raised:
        read_point_cloud(content, format="e57", filename="bad.e57")
    assert str(raised.value).startswith("bad.e57: ")
    with pytest.raises(PointCloudError, match=message):
        summarise_point_cloud(content, format="e57", filename="bad.e57")


@pytest.mark.parametrize("name", ["station", "scan_index", "Station_Index"])
def test_a_station_index_field_of_a_ply_becomes_the_station_index(name):
    points = random_points(60, seed=6)
    station = np.repeat(np.array([0, 1, 2], dtype=np.uint8), 20)

    cloud = read_point_cloud(ply_bytes(points, extra={name: station}), filename="s.ply")

    assert cloud.attributes["station_index"].tolist() == station.tolist()
    assert name not in cloud.attributes
    assert cloud.sensor_origin is None


def test_per_point_origins_of_a_ply_become_stations_in_file_order():
    points = random_points(90, seed=7)
    origins = np.array([[5.0, 5.0, 1.0], [-2.0, 0.0, 1.5], [0.0, 0.0, 1.0]])
    station = np.tile([1, 0, 2], 30)  # the file lists station 1 first
    extra = {f"origin_{axis}": origins[station, i] for i, axis in enumerate("xyz")}

    cloud = read_point_cloud(ply_bytes(points, coordinate_type="f8", extra=extra), filename="o.ply")

    np.testing.assert_allclose(cloud.sensor_origin, origins[[1, 0, 2]])
    np.testing.assert_allclose(
        cloud.sensor_origin[cloud.attributes["station_index"]], origins[station]
    )
    assert not {"origin_x", "origin_y", "origin_z"} & set(cloud.attributes)


def test_per_point_origins_and_station_index_as_las_extra_bytes():
    points = random_points(40, seed=8) * 10
    extra = {
        "origin_x": np.where(np.arange(40) < 25, 1.0, 4.0),
        "origin_y": np.full(40, 2.0),
        "origin_z": np.full(40, 1.25),
    }

    cloud = read_point_cloud(las_bytes(points, extra=extra), filename="o.las")

    assert cloud.sensor_origin.tolist() == [[1.0, 2.0, 1.25], [4.0, 2.0, 1.25]]
    assert cloud.attributes["station_index"].tolist() == [0] * 25 + [1] * 15
    station_only = read_point_cloud(
        las_bytes(points, extra={"station": np.arange(40, dtype=np.int32) % 2}), filename="s.las"
    )
    assert station_only.attributes["station_index"].tolist() == [0, 1] * 20


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        ({"station": np.full(30, 1.5)}, "whole numbers"),
        ({"scan_index": np.full(30, -1, dtype=np.int16)}, "count from 0"),
        ({"origin_x": np.zeros(30)}, "origin_y, origin_z missing"),
        (
            {
                "origin_x": np.r_[np.zeros(29), np.nan],
                "origin_y": np.zeros(30),
                "origin_z": np.zeros(30),
            },
            "row 29",
        ),
        (
            {"origin_x": np.arange(30.0), "origin_y": np.zeros(30), "origin_z": np.zeros(30)},
            None,
        ),
    ],
    ids=["fraction", "negative", "partial-origin", "nan-origin", "too-many-origins"],
)
def test_bad_station_fields_are_refused_with_what_to_fix(extra, message, monkeypatch):
    from app.core.formats import station_fields

    monkeypatch.setattr(station_fields, "MAX_STATIONS", 16)
    content = ply_bytes(random_points(30, seed=9), coordinate_type="f8", extra=extra)
    with pytest.raises(PointCloudError, match=message or "at most 16 stations"):
        read_point_cloud(content, filename="bad.ply")


def in_station_order(pair: LidarPair) -> LidarPair:
    """``pair`` with each cloud's points grouped by station (the order an E57 file gives)."""
    reference_order = np.argsort(pair.reference_station, kind="stable")
    scan_order = np.argsort(pair.scan_station, kind="stable")
    fields = {}
    for field in dataclasses.fields(pair):
        value = getattr(pair, field.name)
        if field.name.startswith("reference") and field.name != "reference_origins":
            fields[field.name] = value[reference_order]
        elif field.name.startswith("scan") and field.name != "scan_origins":
            fields[field.name] = value[scan_order]
    return dataclasses.replace(pair, **fields)


@pytest.fixture(scope="module")
def three_station_room() -> LidarPair:
    """A merged three-station survey of a room with a box added (made once for the module)."""
    return lidar_pair(
        layout="room", change="added", n_stations=3, angular_step_deg=1.2, random_state=3
    )


def test_compare_uses_the_stations_of_e57_files(three_station_room: LidarPair):
    pair = in_station_order(three_station_room)
    reference = read_point_cloud(
        stations_as_e57(pair.reference, pair.reference_station, pair.reference_origins, seed=2),
        filename="reference.e57",
    )
    scan = read_point_cloud(
        stations_as_e57(pair.scan, pair.scan_station, pair.scan_origins, seed=3),
        filename="scan.e57",
    )
    # the points round-trip, so the truth of the pair applies to the clouds read
    np.testing.assert_allclose(scan.points, pair.scan, atol=1e-6)

    result = compare(reference, scan, method="gmm", variant="improved", align=False)

    assert [entry.source for entry in result.sensor_origins["reference"]] == ["file"] * 3
    assert result.localisation["reference_station_assignment"] == "given"
    assert result.localisation["scan_stations"] == 3
    reported = np.array([entry.origin for entry in result.sensor_origins["scan"]])
    np.testing.assert_allclose(reported, pair.scan_origins, atol=1e-6)
    assert result.changed
    assert changed_iou(pair, result) >= 0.9


def test_one_given_origin_for_a_file_of_several_stations_is_refused():
    cloud = read_point_cloud(e57_content(), filename="two.e57")
    with pytest.raises(InputError, match=r"station_index must lie in 0\.\.0"):
        compare(
            cloud,
            cloud,
            method="gmm",
            variant="improved",
            align=False,
            params={"reference_origin": [1.0, 2.0, 3.0]},
        )


def test_a_station_index_alone_gets_each_station_origin_estimated(three_station_room: LidarPair):
    pair = three_station_room
    reference = read_point_cloud(
        ply_bytes(
            pair.reference,
            coordinate_type="f8",
            extra={"station": pair.reference_station.astype(np.int32)},
        ),
        filename="reference.ply",
    )
    scan = read_point_cloud(
        ply_bytes(
            pair.scan,
            coordinate_type="f8",
            extra={"scan_index": pair.scan_station.astype(np.int32)},
        ),
        filename="scan.ply",
    )

    result = compare(reference, scan, method="gmm", variant="improved", align=False)

    for side, truth in (("reference", pair.reference_origins), ("scan", pair.scan_origins)):
        entries = result.sensor_origins[side]
        assert [entry.source for entry in entries] == ["estimated"] * 3
        found = np.array([entry.origin for entry in entries])
        assert np.linalg.norm(found - truth, axis=1).max() < 0.05
    assert result.localisation["scan_station_assignment"] == "given"
    assert result.changed
    assert changed_iou(pair, result) >= 0.9


def test_a_station_index_without_lidar_structure_gets_no_estimated_origins():
    points = np.random.default_rng(8).uniform(0, 10, (9000, 3))
    station = np.repeat([0, 1, 2], 3000)
    assert estimate_each_station("reference", points, station) is None
    with pytest.raises(InputError, match="whole numbers"):
        estimate_each_station("reference", points, station + 0.5)
