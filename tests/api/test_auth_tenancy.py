"""Authentication (401), roles (403), tenancy (404 for other organisations' objects), logs."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import pytest

from app.api.logs import JsonFormatter
from app.config import Settings
from app.testing.files import ply_bytes
from app.testing.scenes import room_points as make_points
from tests.helpers.http import assert_error, create_site, site_with_reference, unique_name, upload
from tests.helpers.jobs import finish_job
from tests.helpers.server import ApiServer


@pytest.mark.parametrize(
    "headers",
    [{}, {"Authorization": "Bearer sdt_not-a-real-token"}, {"Authorization": "Basic dXNlcjpwdw=="}],
    ids=["missing", "unknown", "wrong-scheme"],
)
def test_requests_without_a_valid_token_are_401_with_json(api: ApiServer, headers: dict) -> None:
    client = api.client(headers=headers)
    for response in (
        client.get("/api/v1/sites"),
        client.post("/api/v1/sites", json={"name": "x"}),
        client.get("/api/v1/jobs/0123"),
        client.post("/api/v1/sites/x/scans", content=b"ply\n"),
    ):
        assert_error(response, 401, "unauthorized")
        assert response.headers["www-authenticate"] == "Bearer"


def test_health_is_public(api: ApiServer) -> None:
    response = api.client().get("/api/v1/health")
    assert response.status_code == 200
    body = response.json()
    assert body["database"]["status"] == "ok"
    assert "queue" in body


def test_readers_read_but_cannot_write(api: ApiServer) -> None:
    organisation = unique_name("readers")
    writer = api.client(api.token("writer", organisation))
    reader = api.client(api.token("reader", organisation))
    site, reference = site_with_reference(writer)
    assert reader.get(f"/api/v1/sites/{site['id']}").status_code == 200
    assert reader.get(f"/api/v1/scans/{reference['id']}/file").status_code == 200
    site_path = f"/api/v1/sites/{site['id']}"
    forbidden = [
        reader.post("/api/v1/sites", json={"name": "nope"}),
        reader.patch(site_path, json={"description": "x"}),
        reader.delete(site_path),
        upload(reader, site["id"], ply_bytes(make_points(500))),
        reader.post(f"{site_path}/reference", json={"scan_id": reference["id"]}),
        reader.post(
            "/api/v1/jobs",
            json={"reference_scan_id": reference["id"], "scan_id": reference["id"]},
        ),
    ]
    for response in forbidden:
        assert_error(response, 403, "forbidden")
    assert reader.get(site_path).json()["description"] is None


def test_admins_can_write(api: ApiServer) -> None:
    admin = api.client(api.token("admin"))
    create_site(admin)


def test_organisations_cannot_see_each_others_objects(api: ApiServer) -> None:
    alice = api.client(api.token("writer", unique_name("alice")))
    bob = api.client(api.token("admin", unique_name("bob")))
    site, reference = site_with_reference(alice)
    response = upload(alice, site["id"], ply_bytes(make_points(2500, seed=4)))
    assert response.status_code == 202, response.text
    scan, job = response.json()["scan"], response.json()["job"]
    finish_job(api, job["id"], reference["n_points"], scan["n_points"])
    bob_site = create_site(bob, name=site["name"])  # same name in another organisation is fine

    assert [item["id"] for item in bob.get("/api/v1/sites").json()["items"]] == [bob_site["id"]]
    not_found = [
        bob.get(f"/api/v1/sites/{site['id']}"),
        bob.patch(f"/api/v1/sites/{site['id']}", json={"description": "mine now"}),
        bob.delete(f"/api/v1/sites/{site['id']}"),
        bob.get(f"/api/v1/sites/{site['id']}/scans"),
        bob.get(f"/api/v1/sites/{site['id']}/jobs"),
        upload(bob, site["id"], ply_bytes(make_points(500)), reference=True),
        bob.get(f"/api/v1/scans/{scan['id']}"),
        bob.get(f"/api/v1/scans/{scan['id']}/file"),
        bob.get(f"/api/v1/jobs/{job['id']}"),
        bob.get(f"/api/v1/jobs/{job['id']}/regions"),
        bob.get(f"/api/v1/jobs/{job['id']}/labels"),
        bob.get(f"/api/v1/jobs/{job['id']}/labels", params={"format": "ply"}),
        bob.post(f"/api/v1/sites/{bob_site['id']}/reference", json={"scan_id": scan["id"]}),
        bob.post(
            "/api/v1/jobs", json={"reference_scan_id": reference["id"], "scan_id": scan["id"]}
        ),
    ]
    for response in not_found:
        assert_error(response, 404, "not_found")
    # Alice still has everything.
    assert alice.get(f"/api/v1/sites/{site['id']}").json()["description"] is None
    assert alice.get(f"/api/v1/jobs/{job['id']}/labels").status_code == 200


def test_each_request_is_logged_once_without_the_token(
    api: ApiServer, caplog: pytest.LogCaptureFixture
) -> None:
    token = api.token("writer")
    client = api.client(token, headers={"X-Request-ID": "req-12345"})
    caplog.set_level(logging.INFO, logger="scandiff.api.access")
    response = client.get("/api/v1/sites", params={"limit": 5})
    assert response.headers["x-request-id"] == "req-12345"

    def matching() -> list[logging.LogRecord]:
        return [
            record
            for record in caplog.records
            if record.name == "scandiff.api.access" and record.request_id == "req-12345"
        ]

    deadline = time.monotonic() + 5  # the line is written once the response has been sent
    while not matching() and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(0.05)
    records = matching()
    assert len(records) == 1
    record = records[0]
    assert (record.method, record.path, record.status, record.request_id) == (
        "GET",
        "/api/v1/sites",
        200,
        "req-12345",
    )
    assert record.duration_ms >= 0
    line = JsonFormatter().format(record)
    assert '"request_id": "req-12345"' in line
    assert token not in line
    assert all(token not in JsonFormatter().format(entry) for entry in caplog.records)


def test_token_command_prints_only_a_working_token(
    api: ApiServer, capsys: pytest.CaptureFixture[str]
) -> None:
    from app.cli import main

    status = main(
        ["token", "create", "--org", "cli-org", "--role", "reader", "--data-dir", str(api.data_dir)]
    )
    assert status == 0
    output = capsys.readouterr().out
    token = output.strip()
    assert output == token + "\n"
    client = api.client(token)
    assert client.get("/api/v1/sites").status_code == 200
    assert_error(client.post("/api/v1/sites", json={"name": "x"}), 403)


def test_token_command_migrates_a_fresh_data_directory(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from app.cli import main

    data_dir = tmp_path / "fresh"
    arguments = ["token", "create", "--org", unique_name("o"), "--role", "admin"]
    assert main([*arguments, "--data-dir", str(data_dir)]) == 0
    if Settings(data_dir=data_dir).database_url is None:  # the default embedded database
        assert (data_dir / "scandiff.sqlite3").is_file()
    assert len(capsys.readouterr().out.split()) == 1
    assert (
        main(["token", "create", "--org", " ", "--role", "admin", "--data-dir", str(data_dir)]) == 2
    )


def test_the_dashboard_session_cookie_authenticates_api_requests(api: ApiServer) -> None:
    organisation = unique_name("cookie")
    reader_token = api.token("reader", organisation)
    writer = api.client(api.token("writer", organisation))
    site = create_site(writer)
    browser = api.client()
    assert browser.post("/api/v1/session", json={"token": reader_token}).status_code == 200
    listed = browser.get("/api/v1/sites").json()["items"]
    assert [item["id"] for item in listed] == [site["id"]]
    assert_error(browser.post("/api/v1/sites", json={"name": "x"}), 403)  # still a reader
    # A bearer header, when sent, is what counts (an invalid one is not rescued by the cookie).
    bad = browser.get("/api/v1/sites", headers={"Authorization": "Bearer wrong"})
    assert_error(bad, 401)
    assert_error(api.client().get("/api/v1/sites"), 401)
