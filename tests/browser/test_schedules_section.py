"""The site page's schedules section in a real headless Chromium against ``scandiff serve``:
a refused cron explained in words, a schedule added with the form, run now, its run listed
with a link to its comparison, and the schedule deleted."""

from __future__ import annotations

from typing import Any

import pytest

from tests.helpers.browser import ReviewService, save_screenshot
from tests.helpers.browser import by_css as visible
from tests.helpers.browser import wait_for_page as wait_until
from tests.helpers.http import upload

pytestmark = pytest.mark.timeout(240)


def text_of(driver: Any, selector: str) -> str:
    """Text of every element matching ``selector``."""
    from selenium.webdriver.common.by import By

    return " ".join(element.text for element in driver.find_elements(By.CSS_SELECTOR, selector))


def test_schedules_section_adds_runs_and_deletes_a_schedule(
    review_service: ReviewService, chrome_factory
) -> None:
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select

    service = review_service
    with service.client() as client:
        site = client.post("/api/v1/sites", json={"name": "Scheduled hall"}).json()
        reference = service.files.reference
        answer = upload(
            client, site["id"], reference.read_bytes(), filename=reference.name, reference=True
        )
        assert answer.status_code == 201, answer.text

    driver = chrome_factory()
    driver.get(service.base_url + "/")
    visible(driver, "#token").send_keys(service.process.admin_token)
    visible(driver, "#sign-in-button").click()
    visible(driver, "#new-site-name")
    driver.get(f"{service.base_url}/#/sites/{site['id']}")
    visible(driver, "#schedules-card")
    visible(driver, "#no-schedules")

    # A cron expression with a minute 61 is refused, saying what to give.
    rhythm = visible(driver, "#schedule-rhythm")
    rhythm.clear()
    rhythm.send_keys("61 2 * * *")
    visible(driver, "#create-schedule").click()
    wait_until(
        lambda: "invalid cron expression" in text_of(driver, "#schedule-error"), 20, "no refusal"
    )
    assert "five fields" in text_of(driver, "#schedule-error")

    rhythm.clear()
    rhythm.send_keys("0 2 * * *")
    zone = visible(driver, "#schedule-timezone")
    zone.clear()
    zone.send_keys("Europe/Lisbon")
    Select(visible(driver, "#schedule-catch-up")).select_by_value("each")
    visible(driver, "#create-schedule").click()
    row = visible(driver, "#schedules-table tbody tr")
    assert "cron 0 2 * * * (Europe/Lisbon)" in row.text
    assert "uploads" in row.text and "each" in row.text
    assert text_of(driver, "#schedule-error") == ""

    # Nothing new since the schedule was made: run now records a missed period.
    visible(driver, "#schedules-table .run-now").click()
    wait_until(
        lambda: driver.find_elements(By.CSS_SELECTOR, ".schedule-run[data-status=missed]"),
        30,
        "no missed run listed",
    )
    with service.client() as client:
        scan = service.files.scan
        answer = upload(client, site["id"], scan.read_bytes(), filename=scan.name)
        assert answer.status_code == 202, answer.text
        job_id = answer.json()["job"]["id"]
    visible(driver, "#schedules-table .run-now").click()
    compared = wait_until(
        lambda: driver.find_elements(By.CSS_SELECTOR, ".schedule-run[data-status=compared] a"),
        30,
        "no compared run listed",
    )
    assert compared[0].get_attribute("href").endswith(f"#/jobs/{job_id}")
    save_screenshot(driver, "schedules-section")

    visible(driver, "#schedules-table .delete-schedule").click()
    visible(driver, "#no-schedules")
    with service.client() as client:
        assert client.get(f"/api/v1/sites/{site['id']}/schedules").json() == []
