"""The review inbox and the dashboard's flow (issue 31) in a real headless Chromium: 20 jobs
reviewed by keyboard alone in the inbox, the upload card following its job to the end with a
link to it, a job page opened from a scrolled site page at its top, the schedule form's
detector choice and cron/interval switch, and the webhooks page listing deliveries.

One app for the module, served over HTTP on a migrated SQLite file, without a worker: the tests
play it with :func:`tests.helpers.jobs.finish_job`, so every job ends when the test says.
"""

from __future__ import annotations

from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path
from typing import Any

import httpx
import pytest

from app.clock import utc_now
from app.db.models import DeliveryStatus, Event, Webhook, WebhookDelivery
from app.db.session import transaction
from app.testing.files import ply_bytes
from app.testing.scenes import room_points
from tests.helpers.browser import by_css, save_screenshot, text_of
from tests.helpers.browser import wait_for_page as wait_until
from tests.helpers.http import create_site, unique_name, upload
from tests.helpers.jobs import finish_job, random_regions
from tests.helpers.server import MAX_UPLOAD_BYTES, ApiServer, fresh_api

pytestmark = pytest.mark.timeout(240)

N_REFERENCE = 1500
N_SCAN = 1200


@pytest.fixture(scope="module")
def api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ApiServer]:
    """The app on a fresh, migrated data directory (no worker: tests finish jobs themselves)."""
    yield from fresh_api(tmp_path_factory, "inbox-data", max_upload_bytes=MAX_UPLOAD_BYTES)


def sign_in(driver: Any, api: ApiServer, token: str) -> None:
    """Sign in with the form, as a person would."""
    driver.get(api.base_url + "/")
    by_css(driver, "#token").send_keys(token)
    by_css(driver, "#sign-in-button").click()
    wait_until(lambda: by_css(driver, "#who-text").text, 20, "signing in did not work")


def site_with_reference(client: httpx.Client, name: str) -> dict[str, Any]:
    """A new site named ``name`` (made unique) with a reference scan."""
    site = create_site(client, name=unique_name(name))
    answer = upload(client, site["id"], ply_bytes(room_points(N_REFERENCE, seed=1)), reference=True)
    assert answer.status_code == 201, answer.text
    return site


def finished_job(
    api: ApiServer, client: httpx.Client, site_id: str, seed: int, **result: Any
) -> dict[str, Any]:
    """A scan uploaded to ``site_id`` and its job finished by playing the worker; the job."""
    answer = upload(
        client, site_id, ply_bytes(room_points(N_SCAN, seed=seed)), filename=f"scan-{seed}.ply"
    )
    assert answer.status_code == 202, answer.text
    job = answer.json()["job"]
    finish_job(api, job["id"], N_REFERENCE, N_SCAN, **result)
    return job


def press(driver: Any, *keys: str) -> None:
    """Press ``keys`` one after the other on whatever has the focus (the keyboard alone)."""
    from selenium.webdriver.common.action_chains import ActionChains

    for key in keys:
        ActionChains(driver).send_keys(key).perform()


def focused_job(driver: Any) -> str | None:
    """The job id of the inbox row that has the keyboard focus (the document's active element)."""
    return driver.execute_script(
        "const row = document.activeElement && document.activeElement.closest('.inbox-row');"
        "return row && row.classList.contains('focused') ? row.dataset.jobId : null;"
    )


def test_the_inbox_reviews_20_jobs_by_keyboard_alone(api: ApiServer, chrome_factory) -> None:
    from selenium.webdriver.common.keys import Keys

    token = api.token("writer")
    client = api.client(token)
    north = site_with_reference(client, "North hall")
    south = site_with_reference(client, "South yard")
    waiting = []  # oldest first
    for index in range(20):
        site = north if index % 5 else south  # 16 in the north hall, 4 in the south yard
        waiting.append(
            finished_job(api, client, site["id"], seed=100 + index, changed=index % 2 == 0)
        )
    reviewed = finished_job(api, client, north["id"], seed=200)
    assert (
        client.post(
            f"/api/v1/jobs/{reviewed['id']}/verdict", json={"verdict": "confirmed"}
        ).status_code
        == 200
    )
    queued = upload(client, south["id"], ply_bytes(room_points(N_SCAN, seed=201))).json()["job"]
    newest_first = [job["id"] for job in reversed(waiting)]

    driver = chrome_factory()
    sign_in(driver, api, token)
    by_css(driver, "#inbox-link").click()
    wait_until(lambda: len(driver.find_elements("css selector", ".inbox-row")) == 20, 20, "20 rows")
    rows = driver.find_elements("css selector", ".inbox-row")
    shown = [row.get_attribute("data-job-id") for row in rows]
    assert shown == newest_first  # newest first; neither the reviewed nor the queued job
    assert reviewed["id"] not in shown and queued["id"] not in shown
    assert "(20 awaiting a verdict)" in by_css(driver, "#inbox-title").text
    counts = text_of(driver, "#inbox-counts")
    assert "All sites (20)" in counts
    assert f"{north['name']} (16)" in counts and f"{south['name']} (4)" in counts
    legend = by_css(driver, "#inbox-keys").text
    for key in ("j", "k", "v", "Enter", "c", "f", "r"):
        assert key in legend, legend

    # The focus is visible: the focused row is drawn unlike the others.
    assert focused_job(driver) == newest_first[0]
    style = (
        "const style = getComputedStyle(arguments[0]);"
        "return style.borderTopColor + style.backgroundColor;"
    )
    assert driver.execute_script(style, rows[0]) != driver.execute_script(style, rows[1])

    # Next / previous by j/k and the arrows; the 3D view by v and Enter.
    press(driver, "j", Keys.ARROW_DOWN)
    assert focused_job(driver) == newest_first[2]
    press(driver, "k")
    assert focused_job(driver) == newest_first[1]
    press(driver, Keys.ARROW_UP, Keys.ARROW_UP)  # stays on the first
    assert focused_job(driver) == newest_first[0]
    driver.execute_script(
        "window.opened = []; window.open = (url) => { window.opened.push(url); return null; };"
    )
    press(driver, "v", "j", Keys.ENTER, "k")
    assert driver.execute_script("return window.opened") == [
        f"/jobs/{newest_first[0]}/view",
        f"/jobs/{newest_first[1]}/view",
    ]

    # Review all 20: confirm, false alarm, and twice a new reference (r pressed twice).
    expected = {}
    for index, job_id in enumerate(newest_first):
        assert focused_job(driver) == job_id, index
        if index in (5, 17):
            press(driver, "r")
            assert "Press r again" in by_css(driver, "#inbox-status").text
            press(driver, "r")
            expected[job_id] = "new_reference"
        elif index % 2:
            press(driver, "f")
            expected[job_id] = "false_alarm"
        else:
            press(driver, "c")
            expected[job_id] = "confirmed"
    wait_until(
        lambda: (
            len(driver.find_elements("css selector", ".inbox-row[data-verdict-state=saved]")) == 20
        ),
        30,
        "20 verdicts saved",
    )
    assert "(0 awaiting a verdict)" in by_css(driver, "#inbox-title").text
    save_screenshot(driver, "review-inbox")
    given = {
        job_id: client.get(f"/api/v1/jobs/{job_id}").json()["verdict"]["verdict"]
        for job_id in newest_first
    }
    assert given == expected
    assert (
        client.get("/api/v1/jobs", params={"status": "succeeded", "verdict": "none"}).json()[
            "items"
        ]
        == []
    )
    assert client.get("/api/v1/jobs/awaiting-review/counts").json() == {"total": 0, "sites": []}
    # the last new reference of the north hall is its reference now
    last_north_reference = [
        job_id for job_id in newest_first if expected[job_id] == "new_reference"
    ]
    site = client.get(f"/api/v1/sites/{north['id']}").json()
    jobs_by_id = {job["id"]: job for job in waiting}
    assert site["reference_scan_id"] in {
        jobs_by_id[job_id]["scan_id"] for job_id in last_north_reference
    }


def test_the_upload_card_follows_its_job_to_the_end(
    api: ApiServer, chrome_factory, tmp_path: Path
) -> None:
    token = api.token("writer")
    client = api.client(token)
    site = site_with_reference(client, "Upload hall")
    scan_path = tmp_path / "tuesday.ply"
    scan_path.write_bytes(ply_bytes(room_points(N_SCAN, seed=9)))

    driver = chrome_factory()
    sign_in(driver, api, token)
    driver.get(f"{api.base_url}/#/sites/{site['id']}")
    by_css(driver, "#scan-file").send_keys(str(scan_path))
    by_css(driver, "#upload-scan").click()
    line = wait_until(
        lambda: driver.find_elements("css selector", "#upload-job[data-job-status=queued]"),
        30,
        "the card shows the queued job",
    )
    assert "queued" in line[0].text
    link = by_css(driver, "#upload-job-link")
    job_id = link.get_attribute("href").rsplit("/", 1)[-1]
    assert client.get(f"/api/v1/jobs/{job_id}").json()["scan_filename"] == "tuesday.ply"

    finish_job(api, job_id, N_REFERENCE, N_SCAN, changed=True)
    wait_until(
        lambda: driver.find_elements("css selector", "#upload-job[data-job-status=succeeded]"),
        30,
        "the card follows the job to its end",
    )
    assert "Comparison done: changed, 1 region." in by_css(driver, "#upload-job").text
    by_css(driver, "#upload-job-link").click()
    by_css(driver, "#job-numbers")
    assert driver.current_url.endswith(f"#/jobs/{job_id}")


def test_a_job_page_opened_from_a_scrolled_site_page_is_at_the_top(
    api: ApiServer, chrome_factory
) -> None:
    token = api.token("writer")
    client = api.client(token)
    site = site_with_reference(client, "Tall hall")
    jobs = [
        finished_job(
            api, client, site["id"], seed=300 + index, regions=random_regions(40, seed=index)
        )
        for index in range(14)
    ]

    driver = chrome_factory()
    driver.set_window_size(1280, 700)
    sign_in(driver, api, token)
    driver.get(f"{api.base_url}/#/sites/{site['id']}")
    wait_until(
        lambda: len(driver.find_elements("css selector", "#jobs-table tbody tr")) == 14,
        20,
        "14 jobs",
    )
    driver.execute_script("window.scrollTo(0, document.body.scrollHeight)")
    scrolled = driver.execute_script("return window.scrollY")
    assert scrolled > 600, scrolled
    oldest = driver.find_element("css selector", f"tr[data-job-id='{jobs[0]['id']}'] .job-link")
    driver.execute_script("arguments[0].click()", oldest)  # clicked where it is, no scrolling
    by_css(driver, "#job-numbers")
    wait_until(
        lambda: driver.find_elements("css selector", "#regions-table tbody tr"), 20, "regions"
    )
    assert (
        driver.execute_script("return document.documentElement.scrollHeight") > 700 + scrolled / 2
    )
    assert driver.execute_script("return window.scrollY") == 0
    button = by_css(driver, "#open-3d-view")
    assert driver.execute_script("return arguments[0].getBoundingClientRect().bottom", button) < 700


def test_the_schedule_form_has_a_detector_and_clears_the_cron_for_an_interval(
    api: ApiServer, chrome_factory
) -> None:
    from selenium.webdriver.support.ui import Select

    token = api.token("writer")
    client = api.client(token)
    site = site_with_reference(client, "Scheduled yard")

    driver = chrome_factory()
    sign_in(driver, api, token)
    driver.get(f"{api.base_url}/#/sites/{site['id']}")
    by_css(driver, "#no-schedules")
    rhythm = by_css(driver, "#schedule-rhythm")
    assert rhythm.get_attribute("value") == "0 2 * * *"
    Select(by_css(driver, "#schedule-kind")).select_by_value("interval")
    assert rhythm.get_attribute("value") == ""  # the cron text does not stay
    assert by_css(driver, "#schedule-timezone").get_attribute("disabled") is not None
    Select(by_css(driver, "#schedule-kind")).select_by_value("cron")
    assert rhythm.get_attribute("value") == "0 2 * * *"
    Select(by_css(driver, "#schedule-kind")).select_by_value("interval")

    method = Select(by_css(driver, "#schedule-method"))
    assert method.first_selected_option.get_attribute("value") == ""  # the site's detector
    wait_until(lambda: len(method.options) > 2, 20, "the detector methods")
    assert Select(by_css(driver, "#schedule-variant")).first_selected_option.text == "improved"
    method.select_by_value("pca")
    Select(by_css(driver, "#schedule-variant")).select_by_value("paper")
    rhythm.send_keys("3600")
    by_css(driver, "#schedule-stale").send_keys("7200")
    by_css(driver, "#create-schedule").click()
    row = by_css(driver, "#schedules-table tbody tr")
    assert by_css(driver, "#schedules-table .schedule-detector").text == "pca · paper"
    assert "stale after 2 h" in by_css(driver, "#schedules-table .schedule-staleness").text
    assert "every 3600 s" in row.text
    schedules = client.get(f"/api/v1/sites/{site['id']}/schedules").json()
    schedules = schedules["items"] if isinstance(schedules, dict) else schedules
    assert len(schedules) == 1
    schedule = schedules[0]
    assert (schedule["cron"], schedule["interval_seconds"]) == (None, 3600)
    assert (schedule["detector"]["method"], schedule["detector"]["variant"]) == ("pca", "paper")
    assert schedule["stale_after_seconds"] == 7200


def test_the_webhooks_page_lists_deliveries(api: ApiServer, chrome_factory) -> None:
    token = api.token("admin")
    client = api.client(token)
    organisation_id = client.get("/api/v1/organisation").json()["id"]
    now = utc_now()
    with transaction(api.settings.sqlalchemy_url) as session:
        webhook = Webhook(
            organisation_id=organisation_id,
            url="https://hooks.example.com/scandiff",
            events=["job.changed"],
            secret="whsec_test",
        )
        session.add(webhook)
        session.flush()
        for minutes, status, attempts, error in (
            (3, DeliveryStatus.DELIVERED, 1, None),
            (1, DeliveryStatus.FAILED, 8, "connection refused by hooks.example.com:443"),
        ):
            event = Event(organisation_id=organisation_id, type="job.changed", created_at=now)
            session.add(event)
            session.flush()
            session.add(
                WebhookDelivery(
                    organisation_id=organisation_id,
                    webhook_id=webhook.id,
                    event_id=event.id,
                    event_type="job.changed",
                    status=status,
                    attempts=attempts,
                    max_attempts=8,
                    last_status_code=200 if error is None else None,
                    last_error=error,
                    created_at=now - timedelta(minutes=minutes),
                )
            )
        webhook_id = webhook.id

    driver = chrome_factory()
    sign_in(driver, api, token)
    by_css(driver, "#webhooks-link").click()
    cell = by_css(driver, "#webhooks-table .last-delivery")
    assert cell.get_attribute("data-status") == "failed"
    assert "attempt 8 of 8" in cell.text
    assert "connection refused by hooks.example.com:443" in cell.text
    by_css(driver, "#webhooks-table .deliveries-link").click()
    wait_until(
        lambda: len(driver.find_elements("css selector", "#deliveries-table tbody tr")) == 2,
        20,
        "2 deliveries",
    )
    assert driver.current_url.endswith(f"#/webhooks/{webhook_id}")
    statuses = [
        row.get_attribute("data-status")
        for row in driver.find_elements("css selector", "#deliveries-table tbody tr")
    ]
    assert statuses == ["failed", "delivered"]
    assert "connection refused" in text_of(driver, "#deliveries-table")
