"""Uploads of multi-station clouds over real HTTP: E57 files and lists of sensor origins.

Rules checked:

* an E57 file with several posed scans is accepted (raw and multipart) with each scan's origin
  as the scan's ``sensor_origin`` list; its comparison job runs;
* truncated, scan-less and not-E57 ``.e57`` uploads are a 400 with the reader's reason, and
  leave nothing stored;
* ``sensor_origin`` takes one ``x,y,z`` or a JSON list of stations; a list that does not cover
  the file's per-point station index, or that is not lists of three finite numbers, is a 422
  saying what to fix.
"""

from __future__ import annotations

import json

import httpx
import numpy as np
import pytest

from app.testing.files import e57_bytes, las_bytes, ply_bytes
from app.testing.scenes import room_points
from tests.helpers.http import assert_error, site_with_reference, upload
from tests.helpers.server import ApiServer

ORIGINS = [[1.0, 2.0, 1.5], [6.0, 2.5, 1.2], [3.0, 7.0, 1.4]]


def survey_e57(seed: int = 1) -> bytes:
    """Three posed scans of one room (each in its sensor's frame, identity rotation)."""
    points = room_points(3000, seed, noise=0.003)
    thirds = np.array_split(points, 3)
    return e57_bytes(
        [third - origin for third, origin in zip(thirds, ORIGINS, strict=True)],
        [((1, 0, 0, 0), origin) for origin in ORIGINS],
    )


@pytest.fixture
def site_and_reference(writer: httpx.Client) -> tuple[dict, dict]:
    return site_with_reference(writer)


@pytest.mark.parametrize("multipart", [False, True], ids=["raw", "multipart"])
def test_an_e57_survey_is_accepted_with_each_scan_origin(
    writer: httpx.Client, site_and_reference: tuple[dict, dict], multipart: bool
) -> None:
    site, _ = site_and_reference

    response = upload(writer, site["id"], survey_e57(), filename="survey.e57", multipart=multipart)

    assert response.status_code == 202, response.text
    scan = response.json()["scan"]
    assert scan["format"] == "e57"
    assert scan["n_points"] == 3000
    assert scan["sensor_origin"] == ORIGINS
    assert writer.get(f"/api/v1/scans/{scan['id']}").json()["sensor_origin"] == ORIGINS


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (lambda: survey_e57()[:5000], "unreadable E57 file"),
        (lambda: survey_e57()[:-100], "size in file header not same as actual"),
        (lambda: e57_bytes([]), "holds no scan"),
        (lambda: b"ASTM-E57" + bytes(3000), "unreadable E57 file"),
        (lambda: b"\x00\x01 binary junk \xff" * 50, "not an E57 file"),
    ],
    ids=["truncated", "short-by-100", "no-scan", "zeros", "junk"],
)
def test_bad_e57_uploads_are_400_with_the_reader_reason_and_store_nothing(
    api: ApiServer,
    writer: httpx.Client,
    site_and_reference: tuple[dict, dict],
    content,
    message: str,
) -> None:
    site, reference = site_and_reference
    files_before = api.stored_files()
    body = content()
    for multipart in (False, True):
        response = upload(writer, site["id"], body, filename="bad.e57", multipart=multipart)
        detail = assert_error(response, 400, "malformed_point_cloud")
        assert message in detail
        assert "bad.e57" in detail
    listed = writer.get(f"/api/v1/sites/{site['id']}/scans").json()["items"]
    assert [scan["id"] for scan in listed] == [reference["id"]]
    assert api.stored_files() == files_before


def test_sensor_origin_takes_a_json_list_of_stations(
    writer: httpx.Client, site_and_reference: tuple[dict, dict]
) -> None:
    site, _ = site_and_reference
    points = room_points(900, 3, noise=0.003)
    station = np.repeat(np.arange(3, dtype=np.uint8), 300)
    with_index = ply_bytes(points, extra={"station": station})

    listed = upload(writer, site["id"], with_index, sensor_origin=json.dumps(ORIGINS))
    assert listed.status_code == 202, listed.text
    assert listed.json()["scan"]["sensor_origin"] == ORIGINS

    one_of_one = upload(writer, site["id"], ply_bytes(points), sensor_origin="[[1, 2, 3]]")
    assert one_of_one.status_code == 202, one_of_one.text
    assert one_of_one.json()["scan"]["sensor_origin"] == [1.0, 2.0, 3.0]

    too_few = assert_error(
        upload(writer, site["id"], with_index, sensor_origin=json.dumps(ORIGINS[:2])),
        422,
        "invalid_sensor_origin",
    )
    assert "names 3 stations" in too_few and "one origin per station" in too_few
    las_too_few = assert_error(
        upload(
            writer,
            site["id"],
            las_bytes(points, extra={"scan_index": station.astype(np.int32)}),
            filename="s.las",
            sensor_origin=json.dumps(ORIGINS[:1]),
        ),
        422,
        "invalid_sensor_origin",
    )
    assert "names 3 stations" in las_too_few
    e57_too_few = assert_error(
        upload(writer, site["id"], survey_e57(), filename="s.e57", sensor_origin="0,0,0"),
        422,
        "invalid_sensor_origin",
    )
    assert "gives 1 origin" in e57_too_few


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[[1,2,3],[4,5]]", "station 1's origin must be three numbers"),
        ("[[1,2,3],[4,5,NaN]]", "station 1's origin must be three finite numbers"),
        ("[[1,2,3],[4,5,true]]", "station 1's origin must be three numbers"),
        ("[[1,2,3],", "not valid JSON"),
        ("[1,2]", "sensor_origin must be three numbers"),
        ("1,2,inf", "three finite numbers"),
    ],
)
def test_bad_station_lists_are_422_with_what_to_fix(
    writer: httpx.Client, site_and_reference: tuple[dict, dict], text: str, message: str
) -> None:
    site, _ = site_and_reference
    detail = assert_error(
        upload(writer, site["id"], ply_bytes(room_points(300, 1)), sensor_origin=text),
        422,
        "invalid_sensor_origin",
    )
    assert message in detail
    assert "[[x,y,z],[x,y,z],...]" in detail
