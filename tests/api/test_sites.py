"""Sites: create, read, list with paging, update, delete (rows and files), validation errors."""

from __future__ import annotations

from pathlib import Path

import httpx

from app.db.models import Job, ReferenceHistory, Region, Scan, Site
from app.testing.files import ply_bytes
from app.testing.scenes import room_points as make_points
from tests.helpers.database import count_rows
from tests.helpers.http import assert_error, create_site, site_with_reference, unique_name, upload
from tests.helpers.jobs import finish_job
from tests.helpers.server import ApiServer


def test_create_and_read_a_site_with_the_default_detector(writer: httpx.Client) -> None:
    site = create_site(writer, name="  Warehouse 7  ", description="north hall")
    assert site["name"] == "Warehouse 7"
    assert site["detector"] == {"method": "gmm", "variant": "improved", "params": {}}
    assert site["reference_scan_id"] is None
    assert len(site["id"]) == 32
    assert site["created_at"].endswith("Z")
    assert writer.get(f"/api/v1/sites/{site['id']}").json() == site


def test_create_a_site_with_a_detector(writer: httpx.Client) -> None:
    detector = {"method": "pca", "variant": "paper", "params": {}}
    site = create_site(writer, detector=detector)
    assert site["detector"] == detector


def test_invalid_site_bodies_are_422(writer: httpx.Client) -> None:
    assert_error(writer.post("/api/v1/sites", json={}), 422, "validation_error")
    assert_error(writer.post("/api/v1/sites", json={"name": ""}), 422)
    assert_error(writer.post("/api/v1/sites", json={"name": "a", "colour": "red"}), 422)
    detail = assert_error(
        writer.post(
            "/api/v1/sites", json={"name": "a", "detector": {"method": "magic", "variant": "x"}}
        ),
        422,
        "invalid_detector",
    )
    assert "magic" in detail
    detail = assert_error(
        writer.post(
            "/api/v1/sites",
            json={
                "name": "b",
                "detector": {"method": "gmm", "variant": "improved", "params": {"bogus": 1}},
            },
        ),
        422,
        "invalid_detector",
    )
    assert "bogus" in detail


def test_malformed_json_is_422_in_the_error_shape(writer: httpx.Client) -> None:
    response = writer.post(
        "/api/v1/sites", content=b"{not json", headers={"Content-Type": "application/json"}
    )
    assert_error(response, 422, "validation_error")


def test_duplicate_names_conflict(writer: httpx.Client) -> None:
    create_site(writer, name="twin")
    assert_error(writer.post("/api/v1/sites", json={"name": "twin"}), 409, "site_exists")
    other = create_site(writer, name="other")
    response = writer.patch(f"/api/v1/sites/{other['id']}", json={"name": "twin"})
    assert_error(response, 409, "site_exists")


def test_update_a_site(writer: httpx.Client) -> None:
    site = create_site(writer, description="before")
    response = writer.patch(
        f"/api/v1/sites/{site['id']}",
        json={"description": "after", "detector": {"method": "planes", "variant": "improved"}},
    )
    assert response.status_code == 200, response.text
    updated = response.json()
    assert updated["description"] == "after"
    assert updated["name"] == site["name"]
    assert updated["detector"]["method"] == "planes"
    response = writer.patch(f"/api/v1/sites/{site['id']}", json={"detector": {"method": "x"}})
    assert_error(response, 422)
    assert_error(writer.patch(f"/api/v1/sites/{site['id']}", json={"name": None}), 422)


def test_list_sites_pages_newest_first_with_an_opaque_cursor(api: ApiServer) -> None:
    organisation = unique_name("paging")
    client = api.client(api.token("reader", organisation))
    writer = api.client(api.token("writer", organisation))
    created = [create_site(writer, name=f"s{index}")["id"] for index in range(5)]
    seen: list[str] = []
    cursor = None
    pages = 0
    while True:
        params = {"limit": 2, **({"cursor": cursor} if cursor else {})}
        page = client.get("/api/v1/sites", params=params).json()
        seen += [item["id"] for item in page["items"]]
        pages += 1
        cursor = page["next_cursor"]
        if cursor is None:
            break
    assert seen == created[::-1]
    assert pages == 3
    assert_error(client.get("/api/v1/sites", params={"cursor": "garbage!"}), 400, "bad_cursor")
    assert_error(client.get("/api/v1/sites", params={"limit": 0}), 422)
    assert_error(client.get("/api/v1/sites", params={"limit": 10_000}), 422)


def test_promote_a_scan_to_reference_keeps_history(api: ApiServer, writer: httpx.Client) -> None:
    site, _first = site_with_reference(writer)
    response = upload(writer, site["id"], ply_bytes(make_points(2000, seed=9)))
    second = response.json()["scan"]
    response = writer.post(f"/api/v1/sites/{site['id']}/reference", json={"scan_id": second["id"]})
    assert response.status_code == 200, response.text
    assert response.json()["reference_scan_id"] == second["id"]
    assert count_rows(api, ReferenceHistory, site_id=site["id"]) == 2
    _other_site, other_reference = site_with_reference(writer)
    response = writer.post(
        f"/api/v1/sites/{site['id']}/reference", json={"scan_id": other_reference["id"]}
    )
    assert_error(response, 422, "scan_of_another_site")
    response = writer.post(f"/api/v1/sites/{site['id']}/reference", json={"scan_id": "f" * 32})
    assert_error(response, 404)


def test_delete_a_site_removes_its_rows_and_files(api: ApiServer, writer: httpx.Client) -> None:
    site, reference = site_with_reference(writer)
    response = upload(writer, site["id"], ply_bytes(make_points(2000, seed=5)))
    scan, job = response.json()["scan"], response.json()["job"]
    finish_job(api, job["id"], reference["n_points"], scan["n_points"])
    assert writer.get(f"/api/v1/jobs/{job['id']}/labels", params={"format": "ply"}).is_success
    scan_directory = api.settings.scans_dir / site["id"]
    result_directory = api.settings.results_dir / job["id"]
    assert len(list(scan_directory.iterdir())) == 2
    assert (result_directory / "labels.ply").is_file()

    response = writer.delete(f"/api/v1/sites/{site['id']}")
    assert response.status_code == 204
    assert response.content == b""
    assert_error(writer.get(f"/api/v1/sites/{site['id']}"), 404)
    assert_error(writer.get(f"/api/v1/scans/{scan['id']}"), 404)
    assert_error(writer.get(f"/api/v1/jobs/{job['id']}"), 404)
    assert_error(writer.delete(f"/api/v1/sites/{site['id']}"), 404)
    for model, column in ((Scan, "site_id"), (Job, "site_id"), (ReferenceHistory, "site_id")):
        assert count_rows(api, model, **{column: site["id"]}) == 0
    assert count_rows(api, Region, job_id=job["id"]) == 0
    assert count_rows(api, Site, id=site["id"]) == 0
    assert not scan_directory.exists()
    assert not Path(result_directory).exists()


def test_unknown_routes_and_methods_use_the_error_shape(writer: httpx.Client) -> None:
    assert_error(writer.get("/api/v1/nothing-here"), 404, "not_found")
    assert_error(writer.put("/api/v1/sites"), 405, "method_not_allowed")
    assert_error(writer.get("/api/v1/sites/does-not-exist"), 404, "not_found")


def test_openapi_is_served(api: ApiServer) -> None:
    client = api.client()
    assert client.get("/docs").status_code == 200
    paths = client.get("/openapi.json").json()["paths"]
    for path in (
        "/api/v1/health",
        "/api/v1/sites",
        "/api/v1/sites/{site_id}",
        "/api/v1/sites/{site_id}/scans",
        "/api/v1/sites/{site_id}/reference",
        "/api/v1/sites/{site_id}/jobs",
        "/api/v1/scans/{scan_id}",
        "/api/v1/scans/{scan_id}/file",
        "/api/v1/jobs",
        "/api/v1/jobs/{job_id}",
        "/api/v1/jobs/{job_id}/regions",
        "/api/v1/jobs/{job_id}/labels",
    ):
        assert path in paths, path
    upload_body = paths["/api/v1/sites/{site_id}/scans"]["post"]["requestBody"]["content"]
    assert set(upload_body) == {"application/octet-stream", "multipart/form-data"}
