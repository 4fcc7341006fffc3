"""The dashboard's management tools in a real headless Chromium (issue 19): a site created
with its detector, edited, deleted after a confirmation; its scans with "make reference"; jobs
that name their files; the region table sorted, filtered and paged; re-running a job with
another detector; a file picker that offers what the server reads; a reader sees none of the
tools that change things.  The app runs over HTTP on a migrated SQLite file; the worker is
played by :func:`tests.helpers.jobs.finish_job`.
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from datetime import timedelta
from typing import Any

import httpx
import pytest
from sqlalchemy import update

from app.clock import utc_now
from app.db.models import Job, JobStatus, ReferenceHistory
from app.db.session import transaction
from app.testing.files import ply_bytes
from app.testing.scenes import room_points
from tests.helpers.browser import by_css, retry, save_screenshot, text_of
from tests.helpers.browser import wait_for_page as wait_until
from tests.helpers.database import count_rows
from tests.helpers.http import create_site, unique_name, upload
from tests.helpers.jobs import finish_job, random_regions
from tests.helpers.server import MAX_UPLOAD_BYTES, ApiServer, fresh_api

pytestmark = pytest.mark.timeout(240)

CENTIMETRES = re.compile(r"^-?\d+\.\d\d$")


@pytest.fixture(scope="module")
def api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ApiServer]:
    """The app on a fresh, migrated data directory (no worker: tests finish jobs themselves)."""
    yield from fresh_api(tmp_path_factory, "dashboard-data", max_upload_bytes=MAX_UPLOAD_BYTES)


def sign_in(driver: Any, api: ApiServer, token: str) -> None:
    """Sign in with the form, as a person would."""
    driver.get(api.base_url + "/")
    by_css(driver, "#token").send_keys(token)
    by_css(driver, "#sign-in-button").click()
    wait_until(lambda: by_css(driver, "#who-text").text, 20, "signing in did not work")


def site_with_scans(client: httpx.Client, names: list[str]) -> tuple[dict, list[dict], list[dict]]:
    """A site whose reference is ``names[0]`` and a PCA job per other name; (site, scans, jobs)."""
    site = create_site(client, name=unique_name("Hall"))
    scans, jobs = [], []
    for index, name in enumerate(names):
        response = upload(
            client,
            site["id"],
            ply_bytes(room_points(1500, seed=index + 1)),
            filename=name,
            reference=index == 0,
            **({} if index == 0 else {"method": "pca"}),
        )
        assert response.status_code in (201, 202), response.text
        scans.append(response.json()["scan"])
        if index:
            jobs.append(response.json()["job"])
    return site, scans, jobs


def rows(driver: Any, selector: str) -> list[Any]:
    """Elements matching ``selector`` now."""
    from selenium.webdriver.common.by import By

    return driver.find_elements(By.CSS_SELECTOR, selector)


def test_site_created_with_a_detector_edited_and_deleted(api: ApiServer, chrome_factory) -> None:
    from selenium.webdriver.support.ui import Select

    organisation = unique_name("org")
    writer = api.client(api.token("writer", organisation))
    driver = chrome_factory()
    sign_in(driver, api, api.token("writer", organisation))

    # Create a site with the PCA detector, paper variant and a parameter.
    name = unique_name("Dock")
    by_css(driver, "#new-site-name").send_keys(name)
    methods = [option.text for option in Select(by_css(driver, "#new-site-method")).options]
    assert methods == writer.get("/api/v1/capabilities").json()["detector_methods"]
    Select(by_css(driver, "#new-site-method")).select_by_value("pca")
    Select(by_css(driver, "#new-site-variant")).select_by_value("paper")
    by_css(driver, "#new-site-params").send_keys("{not json")
    by_css(driver, "#create-site").click()
    assert "not valid JSON" in by_css(driver, "#new-site-error").text
    by_css(driver, "#new-site-params").clear()
    by_css(driver, "#new-site-params").send_keys('{"max_points": 1000}')
    by_css(driver, "#create-site").click()
    assert by_css(driver, "#site-name").text == name
    site = next(s for s in writer.get("/api/v1/sites").json()["items"] if s["name"] == name)
    assert site["detector"] == {"method": "pca", "variant": "paper", "params": {"max_points": 1000}}
    assert "pca · paper" in text_of(driver, ".facts")

    # The file picker offers exactly the formats the server reads.
    extensions = writer.get("/api/v1/capabilities").json()["upload_extensions"]
    accept = wait_until(
        lambda: rows(driver, "#scan-file")[0].get_attribute("accept"), 10, "no accept attribute"
    )
    assert accept.split(",") == extensions
    assert ".e57" in accept.split(",")  # read since app/core/formats/e57.py (issue 15)

    # Edit: a refused detector says why; a good edit shows at once.
    by_css(driver, "#edit-site").click()
    Select(by_css(driver, "#edit-site-method")).select_by_value("gmm")
    by_css(driver, "#edit-site-params").clear()
    by_css(driver, "#edit-site-params").send_keys('{"bogus": 1}')
    by_css(driver, "#save-site").click()
    wait_until(lambda: "bogus" in text_of(driver, "#edit-site-error"), 10, "no refusal shown")
    by_css(driver, "#edit-site-params").clear()
    new_name = unique_name("Dock renamed")
    by_css(driver, "#edit-site-name").clear()
    by_css(driver, "#edit-site-name").send_keys(new_name)
    by_css(driver, "#edit-site-description").send_keys("east wing")
    by_css(driver, "#save-site").click()
    wait_until(lambda: by_css(driver, "#site-name").text == new_name, 10, "rename not shown")
    assert "gmm · paper" in text_of(driver, ".facts")
    assert "east wing" in text_of(driver, "main")
    saved = writer.get(f"/api/v1/sites/{site['id']}").json()
    assert (saved["name"], saved["description"]) == (new_name, "east wing")
    assert saved["detector"] == {"method": "gmm", "variant": "paper", "params": {}}
    save_screenshot(driver, "dashboard-site-settings")

    # Delete: cancel keeps the site; a running job refuses (409, shown); then it goes.
    reference = upload(
        writer, site["id"], ply_bytes(room_points(1500, seed=1)), reference=True
    ).json()["scan"]
    job = upload(writer, site["id"], ply_bytes(room_points(1500, seed=2)), method="pca").json()[
        "job"
    ]
    driver.refresh()  # the page now polls: its job is queued
    by_css(driver, f"#jobs-table tr[data-job-id='{job['id']}']")
    by_css(driver, "#delete-site").click()
    dialog = by_css(driver, "#delete-site-dialog")
    assert dialog.get_attribute("open") is not None
    assert new_name in dialog.text and "cannot be undone" in dialog.text
    time.sleep(3.5)  # the page's live refresh (every 1.5 s while a job is queued) passes by
    assert driver.execute_script(
        "return document.querySelector('#delete-site-dialog').matches(':modal')"
    ), "a live refresh of the page dropped the dialog's modality"
    save_screenshot(driver, "dashboard-delete-site")
    by_css(driver, "#cancel-delete-site").click()
    wait_until(lambda: not rows(driver, "#delete-site-dialog[open]"), 10, "cancel kept it open")
    assert writer.get(f"/api/v1/sites/{site['id']}").status_code == 200

    with transaction(api.settings.sqlalchemy_url) as session:
        session.execute(
            update(Job)
            .where(Job.id == job["id"])
            .values(status=JobStatus.RUNNING, lease_expires_at=utc_now() + timedelta(minutes=5))
        )
    retry(lambda: by_css(driver, "#delete-site").click())
    by_css(driver, "#confirm-delete-site").click()
    wait_until(lambda: "running" in text_of(driver, "#delete-site-error"), 10, "no 409 shown")
    assert writer.get(f"/api/v1/sites/{site['id']}").status_code == 200
    with transaction(api.settings.sqlalchemy_url) as session:
        session.execute(update(Job).where(Job.id == job["id"]).values(status=JobStatus.FAILED))
    by_css(driver, "#confirm-delete-site").click()
    wait_until(lambda: rows(driver, "#sites-table, #no-sites"), 10, "not back on the sites")
    assert new_name not in text_of(driver, "main")
    assert writer.get(f"/api/v1/sites/{site['id']}").status_code == 404
    assert writer.get(f"/api/v1/scans/{reference['id']}").status_code == 404
    assert not (api.settings.scans_dir / site["id"]).exists()


def test_scans_list_and_make_reference(api: ApiServer, chrome_factory) -> None:
    organisation = unique_name("org")
    writer = api.client(api.token("writer", organisation))
    site, scans, _jobs = site_with_scans(writer, ["monday.ply", "tuesday.ply", "wednesday.ply"])
    driver = chrome_factory()
    sign_in(driver, api, api.token("writer", organisation))
    driver.get(f"{api.base_url}/#/sites/{site['id']}")
    wait_until(lambda: len(rows(driver, "#scans-table tbody tr")) == 3, 20, "no scans listed")
    names = [cell.text for cell in rows(driver, "#scans-table .scan-filename")]
    assert names == ["wednesday.ply", "tuesday.ply", "monday.ply"]  # newest first
    reference_row = by_css(driver, f"#scans-table tr[data-scan-id='{scans[0]['id']}']")
    assert reference_row.find_elements("css selector", "#current-reference")
    assert len(rows(driver, "#scans-table .make-reference")) == 2

    target = scans[1]
    by_css(driver, f"button.make-reference[data-scan-id='{target['id']}']").click()
    wait_until(
        lambda: rows(driver, f"#scans-table tr[data-scan-id='{target['id']}'] #current-reference"),
        10,
        "the new reference is not marked",
    )
    wait_until(lambda: "tuesday.ply" in text_of(driver, ".facts"), 10, "facts not updated")
    assert writer.get(f"/api/v1/sites/{site['id']}").json()["reference_scan_id"] == target["id"]
    assert count_rows(api, ReferenceHistory, site_id=site["id"]) == 2
    save_screenshot(driver, "dashboard-site-scans")


def test_jobs_name_files_regions_table_and_rerun(api: ApiServer, chrome_factory) -> None:
    from selenium.webdriver.support.ui import Select

    organisation = unique_name("org")
    writer = api.client(api.token("writer", organisation))
    site, scans, jobs = site_with_scans(writer, ["ref-may.ply", "scan-june.ply"])
    regions = random_regions(60, seed=11)
    finish_job(api, jobs[0]["id"], scans[0]["n_points"], scans[1]["n_points"], regions=regions)
    driver = chrome_factory()
    sign_in(driver, api, api.token("writer", organisation))

    # The jobs table names both files.
    driver.get(f"{api.base_url}/#/sites/{site['id']}")
    cell = by_css(driver, f"#jobs-table tr[data-job-id='{jobs[0]['id']}'] .job-files")
    assert cell.text == "scan-june.ply vs ref-may.ply"

    # The job page names them too; the region table pages by 25 with centimetre precision.
    driver.get(f"{api.base_url}/#/jobs/{jobs[0]['id']}")
    assert by_css(driver, "#job-files").text == "scan-june.ply vs ref-may.ply"
    assert by_css(driver, "#job-scan-file").text == "scan-june.ply"
    assert by_css(driver, "#job-reference-file").text == "ref-may.ply"
    wait_until(lambda: len(rows(driver, "#regions-table tbody tr")) == 25, 10, "no first page")
    assert "1–25 of 60" in by_css(driver, "#regions-summary").text
    for row in rows(driver, "#regions-table tbody tr")[:5]:
        cells = [cell.text for cell in row.find_elements("css selector", "td")]
        assert all(CENTIMETRES.match(value) for value in cells[5:7]), cells
        assert all(CENTIMETRES.match(value) for value in cells[3].split(", ")), cells
        assert all(CENTIMETRES.match(value) for value in cells[4].split(" × ")), cells
    by_css(driver, "#regions-next").click()  # each page once the one before has come
    wait_until(
        lambda: "26–50 of 60" in by_css(driver, "#regions-summary").text, 10, "no second page"
    )
    by_css(driver, "#regions-next").click()
    wait_until(lambda: len(rows(driver, "#regions-table tbody tr")) == 10, 10, "no last page")
    assert by_css(driver, "#regions-next").get_attribute("disabled") is not None

    # Filter by kind and minimum points; sort by points (largest first).
    Select(by_css(driver, "#regions-kind")).select_by_value("removed")
    min_points = by_css(driver, "#regions-min-points")
    min_points.clear()
    min_points.send_keys("1500\t")
    expected = sorted(
        (r.n_points for r in regions if r.kind == "removed" and r.n_points >= 1500), reverse=True
    )
    by_css(driver, "button.sort-button[data-sort='n_points']").click()

    def shown_points() -> list[int] | None:
        shown = rows(driver, "#regions-table tbody tr")
        kinds = {row.get_attribute("data-kind") for row in shown}
        points = [int(row.get_attribute("data-points")) for row in shown]
        return points if kinds <= {"removed"} and points == expected[:25] else None

    wait_until(shown_points, 10, f"the table does not show {expected[:25]}")
    assert f"of {len(expected)}" in by_css(driver, "#regions-summary").text
    save_screenshot(driver, "dashboard-regions")

    # Re-run with another detector: a new job on the same files opens.
    by_css(driver, "#rerun-open").click()
    Select(by_css(driver, "#rerun-method")).select_by_value("gmm")
    by_css(driver, "#rerun-params").clear()
    by_css(driver, "#rerun-params").send_keys('{"max_points": 800}')
    by_css(driver, "#rerun-submit").click()
    wait_until(lambda: jobs[0]["id"] not in driver.current_url, 10, "no new job page")
    new_id = driver.current_url.rsplit("/", 1)[-1]
    new_job = writer.get(f"/api/v1/jobs/{new_id}").json()
    assert (new_job["method"], new_job["params"]) == ("gmm", {"max_points": 800})
    assert (new_job["reference_scan_id"], new_job["scan_id"]) == (scans[0]["id"], scans[1]["id"])
    assert by_css(driver, "#job-files").text == "scan-june.ply vs ref-may.ply"


def test_a_reader_gets_no_tools_that_change_things(api: ApiServer, chrome_factory) -> None:
    organisation = unique_name("org")
    writer = api.client(api.token("writer", organisation))
    site, scans, jobs = site_with_scans(writer, ["a.ply", "b.ply"])
    finish_job(api, jobs[0]["id"], scans[0]["n_points"], scans[1]["n_points"])
    driver = chrome_factory()
    sign_in(driver, api, api.token("reader", organisation))
    by_css(driver, "#sites-table")
    assert not rows(driver, "#new-site-form")
    driver.get(f"{api.base_url}/#/sites/{site['id']}")
    wait_until(lambda: len(rows(driver, "#scans-table tbody tr")) == 2, 20, "no scans listed")
    assert not rows(driver, "#edit-site, #delete-site, .make-reference")
    driver.get(f"{api.base_url}/#/jobs/{jobs[0]['id']}")
    by_css(driver, "#regions-table")
    assert not rows(driver, "#rerun-open")
