"""Scan uploads: raw and multipart bodies in PLY, PCD and LAZ; malformed, unknown, oversize and
empty bodies; file names; downloads of the original bytes; nothing left behind on failure."""

from __future__ import annotations

import hashlib
from collections.abc import Iterator

import httpx
import pytest

from app.db.models import JobStatus
from app.testing.files import las_bytes, pcd_bytes, ply_bytes
from app.testing.scenes import room_points as make_points
from tests.helpers.http import assert_error, create_site, site_with_reference, upload
from tests.helpers.server import MAX_UPLOAD_BYTES, ApiServer


@pytest.fixture
def site_and_reference(writer: httpx.Client) -> tuple[dict, dict]:
    return site_with_reference(writer)


def scan_ids(client: httpx.Client, site_id: str) -> list[str]:
    response = client.get(f"/api/v1/sites/{site_id}/scans")
    assert response.status_code == 200, response.text
    return [item["id"] for item in response.json()["items"]]


@pytest.mark.parametrize(
    ("make_content", "filename", "multipart", "expected_format"),
    [
        (lambda points: ply_bytes(points), "scan.ply", False, "ply"),
        (lambda points: ply_bytes(points, "ascii"), "scan.ply", True, "ply"),
        (lambda points: pcd_bytes(points), "scan.pcd", True, "pcd"),
        (lambda points: pcd_bytes(points), "scan.pcd", False, "pcd"),
        (lambda points: las_bytes(points, compress=True), "scan.laz", True, "laz"),
        (
            lambda points: las_bytes(points, compress=True),
            None,
            False,
            "laz",
        ),  # sniffed from the content
        (lambda points: las_bytes(points), "scan.las", False, "las"),
    ],
    ids=[
        "ply-raw",
        "ply-ascii-multipart",
        "pcd-multipart",
        "pcd-raw",
        "laz-multipart",
        "laz-raw-no-name",
        "las-raw",
    ],
)
def test_uploads_in_every_format_create_a_scan_and_a_queued_job(
    writer: httpx.Client,
    site_and_reference: tuple[dict, dict],
    make_content,
    filename: str | None,
    multipart: bool,
    expected_format: str,
) -> None:
    site, reference = site_and_reference
    points = make_points(2000, seed=11)
    content = make_content(points)
    response = upload(writer, site["id"], content, filename=filename, multipart=multipart)
    assert response.status_code == 202, response.text
    scan, job = response.json()["scan"], response.json()["job"]
    assert scan["format"] == expected_format
    assert scan["n_points"] == 2000 and scan["n_dropped"] == 0
    assert scan["size_bytes"] == len(content)
    assert scan["sha256"] == hashlib.sha256(content).hexdigest()
    assert scan["filename"] == (filename or f"scan.{expected_format}")
    for axis in range(3):
        assert scan["bbox_min"][axis] == pytest.approx(points[:, axis].min(), abs=1e-3)
        assert scan["bbox_max"][axis] == pytest.approx(points[:, axis].max(), abs=1e-3)
    assert job["status"] == JobStatus.QUEUED
    assert (job["reference_scan_id"], job["scan_id"]) == (reference["id"], scan["id"])
    assert (job["method"], job["variant"]) == ("gmm", "improved")
    assert writer.get(f"/api/v1/jobs/{job['id']}").json()["id"] == job["id"]
    assert writer.get(f"/api/v1/scans/{scan['id']}").json() == scan
    download = writer.get(f"/api/v1/scans/{scan['id']}/file")
    assert download.status_code == 200
    assert download.content == content


def test_a_reference_upload_is_201_without_a_job_and_replaces_the_reference(
    writer: httpx.Client, site_and_reference: tuple[dict, dict]
) -> None:
    site, first = site_and_reference
    assert writer.get(f"/api/v1/sites/{site['id']}").json()["reference_scan_id"] == first["id"]
    response = upload(
        writer, site["id"], pcd_bytes(make_points(1500)), filename="new.pcd", reference=True
    )
    assert response.status_code == 201, response.text
    assert response.json()["job"] is None
    second = response.json()["scan"]
    assert writer.get(f"/api/v1/sites/{site['id']}").json()["reference_scan_id"] == second["id"]
    assert writer.get(f"/api/v1/sites/{site['id']}/jobs").json()["items"] == []
    response = upload(writer, site["id"], ply_bytes(make_points(1500, seed=2)))
    assert response.json()["job"]["reference_scan_id"] == second["id"]


def test_a_comparison_upload_without_a_reference_is_409(
    api: ApiServer, writer: httpx.Client
) -> None:
    site = create_site(writer)
    detail = assert_error(upload(writer, site["id"], ply_bytes(make_points())), 409, "no_reference")
    assert "reference=true" in detail
    assert not (api.settings.scans_dir / site["id"]).exists()
    assert list(api.settings.tmp_dir.iterdir()) == []


def test_uploads_to_unknown_sites_are_404(writer: httpx.Client) -> None:
    assert_error(upload(writer, "0" * 32, ply_bytes(make_points(500))), 404, "not_found")


def test_detector_overrides_are_validated_before_the_body_and_used(
    writer: httpx.Client, site_and_reference: tuple[dict, dict]
) -> None:
    site, _ = site_and_reference
    detail = assert_error(
        upload(writer, site["id"], ply_bytes(make_points(500)), method="nonsense"),
        422,
        "invalid_detector",
    )
    assert "nonsense" in detail
    response = upload(writer, site["id"], ply_bytes(make_points(500)), method="pca")
    assert response.status_code == 202, response.text
    assert (response.json()["job"]["method"], response.json()["job"]["variant"]) == (
        "pca",
        "improved",
    )
    response = upload(writer, site["id"], ply_bytes(make_points(500)), variant="paper")
    assert response.json()["job"]["variant"] == "paper"


@pytest.mark.parametrize(
    ("content", "filename", "status", "error", "message"),
    [
        (
            b"ply\nformat binary_little_endian 1.0\nelement vertex 5000\nproperty float x\n"
            b"property float y\nproperty float z\nend_header\n" + b"\0" * 100,
            "broken.ply",
            400,
            "malformed_point_cloud",
            "broken.ply",
        ),
        (
            b"\x00\x01\x02 definitely not a point cloud \xff" * 20,
            "mystery.bin",
            415,
            "unsupported_format",
            "supported formats",
        ),
        (
            b"\x00\x01\x02 definitely not a point cloud \xff" * 20,
            None,
            415,
            "unsupported_format",
            "supported formats",
        ),
        (b"ply\n", "tiny.ply", 400, "malformed_point_cloud", "tiny.ply"),
        (b"", "empty.ply", 400, "empty_upload", "empty"),
    ],
    ids=["truncated-ply", "unknown-suffix", "unknown-content", "header-only", "empty"],
)
def test_bad_files_are_4xx_with_the_core_message_and_leave_nothing(
    api: ApiServer,
    writer: httpx.Client,
    site_and_reference: tuple[dict, dict],
    content: bytes,
    filename: str | None,
    status: int,
    error: str,
    message: str,
) -> None:
    site, reference = site_and_reference
    files_before = api.stored_files()
    for multipart in (False, True):
        response = upload(writer, site["id"], content, filename=filename, multipart=multipart)
        detail = assert_error(response, status, error)
        assert message in detail
    assert scan_ids(writer, site["id"]) == [reference["id"]]
    assert writer.get(f"/api/v1/sites/{site['id']}/jobs").json()["items"] == []
    assert api.stored_files() == files_before


def test_oversize_uploads_are_413_and_store_nothing(
    api: ApiServer, writer: httpx.Client, site_and_reference: tuple[dict, dict]
) -> None:
    site, reference = site_and_reference
    files_before = api.stored_files()
    too_big = b"ply\n" + b"0" * MAX_UPLOAD_BYTES

    def chunked() -> Iterator[bytes]:  # no Content-Length: the streamed count must trip
        for start in range(0, len(too_big), 32_768):
            yield too_big[start : start + 32_768]

    responses = [
        upload(writer, site["id"], too_big),
        upload(writer, site["id"], too_big, multipart=True),
        writer.post(
            f"/api/v1/sites/{site['id']}/scans", params={"filename": "big.ply"}, content=chunked()
        ),
    ]
    for response in responses:
        detail = assert_error(response, 413, "payload_too_large")
        assert str(MAX_UPLOAD_BYTES) in detail
    assert scan_ids(writer, site["id"]) == [reference["id"]]
    assert api.stored_files() == files_before


def test_a_multipart_form_without_a_file_field_is_422(
    writer: httpx.Client, site_and_reference: tuple[dict, dict]
) -> None:
    site, _ = site_and_reference
    response = writer.post(
        f"/api/v1/sites/{site['id']}/scans",
        files={"document": ("scan.ply", ply_bytes(make_points(500)), "application/octet-stream")},
    )
    assert_error(response, 422, "missing_file_field")
    response = writer.post(
        f"/api/v1/sites/{site['id']}/scans",
        content=b"--abc\r\nbroken",
        headers={"Content-Type": "multipart/form-data; boundary=abc"},
    )
    assert response.status_code in (400, 422), response.text
    assert_error(response, response.status_code)


def multipart_with_raw_filename(raw_filename: bytes, content: bytes) -> tuple[bytes, str]:
    boundary = "scandiffboundary"
    body = (
        f"--{boundary}\r\n".encode()
        + b'Content-Disposition: form-data; name="file"; filename="'
        + raw_filename
        + b'"\r\nContent-Type: application/octet-stream\r\n\r\n'
        + content
        + f"\r\n--{boundary}--\r\n".encode()
    )
    return body, f"multipart/form-data; boundary={boundary}"


def test_file_names_are_sanitised(
    writer: httpx.Client, site_and_reference: tuple[dict, dict]
) -> None:
    site, _ = site_and_reference
    content = ply_bytes(make_points(500))
    response = upload(writer, site["id"], content, filename="../../etc/passwd.ply")
    assert response.status_code == 202, response.text
    assert response.json()["scan"]["filename"] == "passwd.ply"
    response = upload(writer, site["id"], content, filename="C:\\scans\\Straße 1.ply")
    assert response.json()["scan"]["filename"] == "Straße 1.ply"
    body, content_type = multipart_with_raw_filename(b"\xff\xfe/../ev\x00il\x07.ply", content)
    response = writer.post(
        f"/api/v1/sites/{site['id']}/scans", content=body, headers={"Content-Type": content_type}
    )
    assert response.status_code == 202, response.text
    scan = response.json()["scan"]
    assert scan["filename"] == "ev_il_.ply"
    assert scan["format"] == "ply"
    download = writer.get(f"/api/v1/scans/{scan['id']}/file")
    assert download.content == content
    assert "ev_il_.ply" in download.headers["content-disposition"]
    body, content_type = multipart_with_raw_filename("mesure-é.ply".encode("latin-1"), content)
    response = writer.post(
        f"/api/v1/sites/{site['id']}/scans", content=body, headers={"Content-Type": content_type}
    )
    assert response.status_code == 202, response.text
    assert response.json()["scan"]["filename"].startswith("mesure-")


def test_files_are_stored_under_ids_not_client_names(
    api: ApiServer, writer: httpx.Client, site_and_reference: tuple[dict, dict]
) -> None:
    site, _ = site_and_reference
    response = upload(writer, site["id"], ply_bytes(make_points(500)), filename="../../x.ply")
    scan = response.json()["scan"]
    stored = api.settings.scans_dir / site["id"] / f"{scan['id']}.ply"
    assert stored.is_file()
    assert list(api.settings.tmp_dir.iterdir()) == []


def test_sensor_origin_comes_from_the_query_or_the_file_and_is_validated(
    writer: httpx.Client, site_and_reference: tuple[dict, dict]
) -> None:
    site, _ = site_and_reference
    points = make_points(3000, seed=4)

    given = upload(writer, site["id"], ply_bytes(points), sensor_origin="1.5,-2,0.25")
    assert given.status_code == 202, given.text
    assert given.json()["scan"]["sensor_origin"] == [1.5, -2.0, 0.25]

    without = upload(writer, site["id"], ply_bytes(points))
    assert without.json()["scan"]["sensor_origin"] is None

    header, body = pcd_bytes(points).split(b"DATA binary\n", 1)
    header = b"\n".join(
        b"VIEWPOINT 3 4 5 1 0 0 0" if line.startswith(b"VIEWPOINT") else line
        for line in header.split(b"\n")
    )
    from_file = upload(writer, site["id"], header + b"DATA binary\n" + body, filename="v.pcd")
    assert from_file.status_code == 202, from_file.text
    assert from_file.json()["scan"]["sensor_origin"] == [3.0, 4.0, 5.0]

    before = scan_ids(writer, site["id"])
    for bad in ("1,2", "a,b,c", "1,2,nan", "1,2,3,4"):
        detail = assert_error(
            upload(writer, site["id"], ply_bytes(points), sensor_origin=bad),
            422,
            "invalid_sensor_origin",
        )
        assert "x,y,z" in detail
    assert scan_ids(writer, site["id"]) == before
