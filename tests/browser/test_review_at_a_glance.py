"""Issue 19 in a real headless Chromium against ``scandiff serve``: the jobs table's warning
badges, the job page's explanation and warnings panel, "failed, will not retry", and the API
docs (/docs, /redoc) rendered with every non-local host unreachable."""

from __future__ import annotations

import json
from typing import Any

import pytest

from tests.helpers.browser import ReviewService, save_screenshot, wait_for_page
from tests.helpers.browser import by_css as visible
from tests.helpers.http import upload

pytestmark = pytest.mark.timeout(300)

OFFLINE = "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1"
"""Chromium resolves no host name but 127.0.0.1: a CDN request fails as it would offline."""

CDN_PROBE = "https://cdn.jsdelivr.net/npm/swagger-ui-dist@5/swagger-ui-bundle.js"


def elements(driver: Any, selector: str) -> list[Any]:
    from selenium.webdriver.common.by import By

    return driver.find_elements(By.CSS_SELECTOR, selector)


def sign_in(driver: Any, service: ReviewService) -> None:
    driver.get(service.base_url + "/")
    visible(driver, "#token").send_keys(service.process.admin_token)
    visible(driver, "#sign-in-button").click()
    visible(driver, "#new-site-name")


@pytest.fixture(scope="module")
def review_jobs(review_service: ReviewService) -> dict[str, Any]:
    """A site with a succeeded upload job, a job told a wrong reference origin (warned), and
    a failed one (max_attempts 1: it will not retry); every job as the API reads it."""
    service = review_service
    files = service.files
    with service.client() as client:
        site = client.post("/api/v1/sites", json={"name": "Warned site"}).json()
        reference = upload(
            client, site["id"], files.reference.read_bytes(), filename=files.reference.name,
            reference=True,
        ).json()["scan"]  # fmt: skip
        uploaded = upload(client, site["id"], files.scan.read_bytes(), filename=files.scan.name)
        assert uploaded.status_code == 202, uploaded.text
        scan_id = uploaded.json()["scan"]["id"]
        warned = client.post(
            "/api/v1/jobs",
            json={
                "reference_scan_id": reference["id"],
                "scan_id": scan_id,
                "params": {"reference_origin": [500.0, 500.0, 500.0]},
            },
        )
        assert warned.status_code == 202, warned.text
        failing = upload(
            client, site["id"], files.failing_scan.read_bytes(), filename=files.failing_scan.name
        )
        ids = {
            "upload": uploaded.json()["job"]["id"],
            "warned": warned.json()["id"],
            "failed": failing.json()["job"]["id"],
        }
        jobs = {
            name: service.process.wait_for_job(client, job_id, timeout=180)
            for name, job_id in ids.items()
        }
    assert jobs["upload"]["status"] == jobs["warned"]["status"] == "succeeded"
    assert jobs["failed"]["status"] == "failed"
    return {"site": site, "jobs": jobs}


def test_the_jobs_table_shows_each_jobs_warnings(
    review_service: ReviewService, review_jobs: dict[str, Any], chrome_factory
) -> None:
    jobs = review_jobs["jobs"]
    warned = jobs["warned"]
    assert "sensor_origin" in [w["code"] for w in warned["warnings"]], warned["warnings"]
    driver = chrome_factory()
    sign_in(driver, review_service)
    driver.get(f"{review_service.base_url}/#/sites/{review_jobs['site']['id']}")
    visible(driver, "#jobs-table")
    for job in jobs.values():
        row = f'#jobs-table tr[data-job-id="{job["id"]}"]'
        visible(driver, row)
        badges = elements(driver, f"{row} .badge-warn")
        warnings = job["warnings"] or []
        assert len(badges) == (1 if warnings else 0), (job["id"], warnings)
        if warnings:
            badge = badges[0]
            assert badge.get_attribute("data-warning-count") == str(len(warnings))
            assert badge.get_attribute("data-warning-codes").split() == [
                w["code"] for w in warnings
            ]
            assert badge.get_attribute("title") == "\n".join(w["message"] for w in warnings)
    driver.execute_script("document.querySelector('#jobs-table').scrollIntoView()")
    save_screenshot(driver, "jobs-warning-badges", docs_name="jobs-warning-badges.png")


def test_the_job_page_explains_the_decision_and_lists_the_warnings(
    review_service: ReviewService, review_jobs: dict[str, Any], chrome_factory
) -> None:
    warned = review_jobs["jobs"]["warned"]
    driver = chrome_factory()
    sign_in(driver, review_service)
    driver.get(f"{review_service.base_url}/#/jobs/{warned['id']}")
    text = visible(driver, "#job-explanation-text").text
    assert text == warned["explanation"]["text"]
    assert text.startswith("changed: " if warned["changed"] else "no change: ")
    panel = visible(driver, "#job-warnings")
    items = elements(driver, "#job-warnings li")
    assert [item.get_attribute("data-code") for item in items] == [
        w["code"] for w in warned["warnings"]
    ]
    for item, warning in zip(items, warned["warnings"], strict=True):
        assert warning["message"] in item.text
    assert f"Quality warnings ({len(warned['warnings'])})" in panel.text
    numbers = visible(driver, "#job-numbers").text
    assert "Sensor origins" in numbers and "reference: " in numbers
    save_screenshot(driver, "job-explanation-warnings", docs_name="job-warnings.png")


def test_a_failed_job_says_it_will_not_retry(
    review_service: ReviewService, review_jobs: dict[str, Any], chrome_factory
) -> None:
    failed = review_jobs["jobs"]["failed"]
    assert failed["will_retry"] is False
    driver = chrome_factory()
    sign_in(driver, review_service)
    driver.get(f"{review_service.base_url}/#/jobs/{failed['id']}")
    assert visible(driver, "#job-retry").text.startswith("failed, will not retry")
    assert "Attempts: " not in visible(driver, "#job-error").text
    assert "failed, will not retry" in visible(driver, "#job-numbers").text


def test_docs_render_with_the_network_blocked(
    review_service: ReviewService, chrome_factory
) -> None:
    base = review_service.base_url
    driver = chrome_factory(OFFLINE, performance_log=True)
    driver.set_script_timeout(30)
    driver.get(f"{base}/")
    # the block is real: from a page without a policy, the stock page's CDN is unreachable
    outcome = driver.execute_async_script(
        "const done = arguments[arguments.length - 1];"
        "fetch(arguments[0]).then(() => done('reached'), (error) => done('failed: ' + error));",
        CDN_PROBE,
    )
    assert outcome.startswith("failed"), outcome
    driver.get_log("performance")  # only the docs' own events below
    driver.get(f"{base}/docs")
    wait_for_page(
        lambda: len(elements(driver, ".swagger-ui .opblock")) >= 5, 60, "Swagger UI not rendered"
    )
    paths = {e.text for e in elements(driver, ".swagger-ui .opblock-summary-path")}
    assert "/api/v1/jobs/{job_id}" in {path.replace("\u200b", "") for path in paths}
    resources = driver.execute_script(
        "return performance.getEntriesByType('resource').map(entry => entry.name)"
    )
    assert resources and all(name.startswith(base) for name in resources), resources
    driver.get_log("performance")  # read: the ReDoc check below sees its own page's events
    save_screenshot(driver, "docs-offline")

    driver.get(f"{base}/redoc")
    wait_for_page(
        lambda: len(elements(driver, "[data-section-id^='operation/']")) >= 5,
        60,
        "ReDoc not rendered",
    )
    assert "scandiff" in visible(driver, "h1").text
    # ReDoc draws its maker's logo from their CDN: the page's policy refuses it in the browser
    off_machine = [
        name
        for name in driver.execute_script(
            "return performance.getEntriesByType('resource').map(entry => entry.name)"
        )
        if not name.startswith(base)
    ]
    blocked = refused_by_policy(driver)
    assert set(off_machine) <= blocked, (off_machine, blocked)
    save_screenshot(driver, "redoc-offline")


def refused_by_policy(driver: Any) -> set[str]:
    """URLs the page asked for that Chromium refused by Content-Security-Policy (never sent)."""
    requested: dict[str, str] = {}
    refused = set()
    for entry in driver.get_log("performance"):
        message = json.loads(entry["message"])["message"]
        params = message.get("params", {})
        if message["method"] == "Network.requestWillBeSent":
            requested[params["requestId"]] = params["request"]["url"]
        elif message["method"] == "Network.loadingFailed" and params.get("blockedReason") == "csp":
            refused.add(requested.get(params["requestId"], ""))
    return refused
