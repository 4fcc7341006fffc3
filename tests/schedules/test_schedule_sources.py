"""Directory and URL sources: the files a run ingests, and what is refused (nothing stored)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from app.db.models import Scan, ScheduleRun
from app.testing.files import room_ply
from tests.helpers.database import count_rows
from tests.helpers.file_server import serving_files
from tests.helpers.http import assert_error, site_with_reference, upload_accepted
from tests.helpers.server import MAX_UPLOAD_BYTES, ApiServer, fresh_api

NIGHTLY = {"cron": "0 2 * * *", "timezone": "Europe/Lisbon"}


def schedule_with_source(client: httpx.Client, site_id: str, source: Any) -> httpx.Response:
    """POST a nightly schedule of ``site_id`` reading ``source``."""
    return client.post(f"/api/v1/sites/{site_id}/schedules", json={**NIGHTLY, "source": source})


def run_now(client: httpx.Client, schedule_id: str) -> httpx.Response:
    """Run a schedule now."""
    return client.post(f"/api/v1/schedules/{schedule_id}/run")


def site_scans(api: ApiServer, site_id: str) -> int:
    """How many scans the site has."""
    return count_rows(api, Scan, site_id=site_id)


def stored_scan_files(api: ApiServer, site_id: str) -> list[Path]:
    """The scan files stored for the site, and the temporary files left anywhere."""
    return [
        path
        for path in api.stored_files()
        if path.parent.name == site_id or path.parent == api.settings.tmp_dir
    ]


def write_file(path: Path, content: bytes, mtime: float | None = None) -> Path:
    """Write ``content`` at ``path`` (and set its modification time)."""
    path.write_bytes(content)
    if mtime is not None:
        os.utime(path, (mtime, mtime))
    return path


def test_a_directory_source_ingests_the_newest_new_file(
    api: ApiServer, writer: httpx.Client, drop_root: Path
) -> None:
    site, reference = site_with_reference(writer)
    directory = drop_root / "site-a"
    directory.mkdir()
    response = schedule_with_source(writer, site["id"], {"directory": str(directory)})
    assert response.status_code == 201, response.text
    schedule = response.json()
    assert schedule["source"] == {"directory": str(directory)}

    missed = run_now(writer, schedule["id"])
    assert missed.status_code == 201, missed.text
    assert missed.json()["status"] == "missed"

    write_file(directory / "older.ply", room_ply(4), mtime=1_700_000_000)
    write_file(directory / "newest.ply", room_ply(5, with_box=True), mtime=1_700_000_100)
    write_file(directory / "copying.ply.part", b"half a file", mtime=1_800_000_000)
    run = run_now(writer, schedule["id"]).json()
    assert run["status"] == "compared", run
    scan = writer.get(f"/api/v1/scans/{run['scan_id']}").json()
    assert scan["filename"] == "newest.ply"
    job = writer.get(f"/api/v1/jobs/{run['job_id']}").json()
    assert job["scan_id"] == run["scan_id"]
    assert job["reference_scan_id"] == reference["id"]
    # nothing new in the directory (an upload through the API is not its source): missed
    upload_accepted(writer, site["id"], "pushed.ply", room_ply(8))
    assert run_now(writer, schedule["id"]).json()["status"] == "missed"
    write_file(directory / "later.ply", room_ply(6), mtime=1_700_000_200)
    assert run_now(writer, schedule["id"]).json()["status"] == "compared"
    assert site_scans(api, site["id"]) == 4  # the reference, the upload, two ingested files


def test_directory_traversal_and_symlinks_out_of_the_root_are_refused(
    api: ApiServer, writer: httpx.Client, drop_root: Path, tmp_path: Path
) -> None:
    site, _reference = site_with_reference(writer)
    outside = tmp_path / "outside"
    outside.mkdir()
    write_file(outside / "secret.ply", room_ply(9))
    (drop_root / "inside").mkdir()
    (drop_root / "escape").symlink_to(outside, target_is_directory=True)
    for directory in (
        f"{drop_root}/../outside",
        f"{drop_root}/inside/../../outside",
        str(drop_root / "escape"),
        "relative/path",
        str(outside),
    ):
        detail = assert_error(
            schedule_with_source(writer, site["id"], {"directory": directory}),
            422,
            "directory_not_allowed",
        )
        assert str(drop_root) in detail or "absolute" in detail
    # a file that is a symlink out of the root: refused when the schedule is created...
    linked = drop_root / "linked"
    linked.mkdir()
    (linked / "scan.ply").symlink_to(outside / "secret.ply")
    assert_error(
        schedule_with_source(writer, site["id"], {"directory": str(linked)}),
        422,
        "directory_not_allowed",
    )
    # ...and when it runs
    later = drop_root / "later"
    later.mkdir()
    schedule = schedule_with_source(writer, site["id"], {"directory": str(later)}).json()
    (later / "scan.ply").symlink_to(outside / "secret.ply")
    detail = assert_error(run_now(writer, schedule["id"]), 422, "directory_not_allowed")
    assert "symlink" in detail
    assert site_scans(api, site["id"]) == 1
    assert len(stored_scan_files(api, site["id"])) == 1  # the reference only
    (run,) = writer.get(f"/api/v1/schedules/{schedule['id']}/runs").json()["items"]
    assert run["status"] == "failed"
    assert "symlink" in run["error"]


def test_files_over_the_upload_cap_are_refused_and_nothing_is_stored(
    api: ApiServer, writer: httpx.Client, drop_root: Path
) -> None:
    site, _reference = site_with_reference(writer)
    huge_at_creation = drop_root / "huge-now"
    huge_at_creation.mkdir()
    with open(huge_at_creation / "huge.ply", "wb") as huge:
        huge.truncate(MAX_UPLOAD_BYTES + 1)
    detail = assert_error(
        schedule_with_source(writer, site["id"], {"directory": str(huge_at_creation)}), 413
    )
    assert "huge.ply" in detail
    huge_later = drop_root / "huge-later"
    huge_later.mkdir()
    schedule = schedule_with_source(writer, site["id"], {"directory": str(huge_later)}).json()
    with open(huge_later / "huge.ply", "wb") as huge:
        huge.truncate(50 * MAX_UPLOAD_BYTES)
    assert_error(run_now(writer, schedule["id"]), 413)
    assert site_scans(api, site["id"]) == 1
    assert len(stored_scan_files(api, site["id"])) == 1
    # a malformed file is refused with the reader's message, and nothing is stored either
    write_file(huge_later / "broken.ply", b"ply\nformat nonsense\n", mtime=4_000_000_000)
    response = run_now(writer, schedule["id"])
    assert 400 <= response.status_code < 500, response.text
    assert site_scans(api, site["id"]) == 1
    assert len(stored_scan_files(api, site["id"])) == 1
    assert count_rows(api, ScheduleRun, schedule_id=schedule["id"], status="failed") == 2


@pytest.fixture
def private_url_api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ApiServer]:
    """The app allowing URL sources on private addresses (the local file server)."""
    yield from fresh_api(
        tmp_path_factory,
        "schedules-url-data",
        max_upload_bytes=MAX_UPLOAD_BYTES,
        allow_private_addresses=True,
        schedule_fetch_timeout_seconds=10.0,
    )


def test_a_url_source_fetches_each_new_file(private_url_api: ApiServer) -> None:
    api = private_url_api
    writer = api.client(api.token("writer"))
    site, _reference = site_with_reference(writer)
    with serving_files({"/latest.ply": room_ply(5, with_box=True)}) as server:
        response = schedule_with_source(writer, site["id"], {"url": server.url("/latest.ply")})
        assert response.status_code == 201, response.text
        schedule = response.json()
        run = run_now(writer, schedule["id"]).json()
        assert run["status"] == "compared", run
        assert writer.get(f"/api/v1/scans/{run['scan_id']}").json()["filename"] == "latest.ply"
        # the same bytes again: nothing new
        assert run_now(writer, schedule["id"]).json()["status"] == "missed"
        server.files["/latest.ply"] = room_ply(6)
        assert run_now(writer, schedule["id"]).json()["status"] == "compared"
        assert server.requests == ["/latest.ply"] * 3
        # too large, or an error answer: refused, nothing stored
        server.files["/latest.ply"] = b"x" * (MAX_UPLOAD_BYTES + 1)
        assert_error(run_now(writer, schedule["id"]), 413)
        gone = schedule_with_source(writer, site["id"], {"url": server.url("/gone.ply")}).json()
        detail = assert_error(run_now(writer, gone["id"]), 422, "fetch_failed")
        assert "404" in detail
    assert site_scans(api, site["id"]) == 3
    assert len(stored_scan_files(api, site["id"])) == 3


def test_a_url_on_loopback_is_refused_unless_allowed(api: ApiServer, writer: httpx.Client) -> None:
    site, _reference = site_with_reference(writer)
    with serving_files({"/latest.ply": room_ply(5)}) as server:
        for url in (server.url("/latest.ply"), f"http://localhost:{server.port}/latest.ply"):
            detail = assert_error(
                schedule_with_source(writer, site["id"], {"url": url}),
                422,
                "forbidden_url_address",
            )
            assert "(loopback)" in detail or "localhost is a loopback address" in detail
        assert server.requests == []
