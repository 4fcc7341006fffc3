"""A job compared tile by tile shows its tiles done/total, over HTTP and on the dashboard
(issue 30's fan-out), in a real headless Chromium.  No worker: the test writes the job's state
as the workers would (a running job, five tiles of which two are stored)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from sqlalchemy import update

from app.db.models import Job, JobStatus, JobTile, TileStatus
from app.db.session import transaction
from app.testing.files import ply_bytes
from app.testing.scenes import room_points
from tests.helpers.browser import by_css, wait_for_page
from tests.helpers.http import create_site, unique_name, upload
from tests.helpers.server import MAX_UPLOAD_BYTES, ApiServer, fresh_api

pytestmark = pytest.mark.timeout(240)


@pytest.fixture(scope="module")
def api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ApiServer]:
    """The app on a fresh, migrated data directory (no worker)."""
    yield from fresh_api(tmp_path_factory, "tile-progress-data", max_upload_bytes=MAX_UPLOAD_BYTES)


def test_a_tiled_job_shows_tiles_done_of_total(api: ApiServer, chrome_factory) -> None:
    token = api.token("writer", unique_name("org"))
    client = api.client(token)
    site = create_site(client)
    for index, name in enumerate(["monday.ply", "tuesday.ply"]):
        response = upload(
            client,
            site["id"],
            ply_bytes(room_points(1500, seed=index + 1)),
            filename=name,
            reference=index == 0,
        )
        assert response.status_code in (201, 202), response.text
    job_id = response.json()["job"]["id"]
    assert client.get(f"/api/v1/jobs/{job_id}").json()["tiles"] is None  # not tiled (yet)

    with transaction(api.settings.sqlalchemy_url) as session:
        session.execute(
            update(Job)
            .where(Job.id == job_id)
            .values(status=JobStatus.RUNNING, progress=0.5, stage="localise")
        )
        session.add_all(
            JobTile(
                job_id=job_id,
                tile_index=index,
                status=TileStatus.SUCCEEDED if index < 2 else TileStatus.QUEUED,
            )
            for index in range(5)
        )
    assert client.get(f"/api/v1/jobs/{job_id}").json()["tiles"] == {"done": 2, "total": 5}

    driver = chrome_factory()
    driver.get(api.base_url + "/")
    by_css(driver, "#token").send_keys(token)
    by_css(driver, "#sign-in-button").click()
    wait_for_page(lambda: by_css(driver, "#who-text").text, 20, "signing in did not work")
    driver.get(f"{api.base_url}/#/jobs/{job_id}")
    wait_for_page(
        lambda: "tiles 2/5" in by_css(driver, ".progress-text").text,
        20,
        "the job page does not show the tiles done",
    )
    driver.get(f"{api.base_url}/#/sites/{site['id']}")
    row = f"#jobs-table tr[data-job-id='{job_id}'] .progress-text"
    wait_for_page(lambda: "tiles 2/5" in by_css(driver, row).text, 20, "the site page neither")
