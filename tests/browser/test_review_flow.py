"""A person's review in a real headless Chromium, against the real service (``scandiff serve``).

Everything a reviewer does is done with the mouse and keyboard in the page: sign in with the
printed token, create a site, upload a reference and a scan (with the progress bar), watch the
job finish live, read the regions, download labels, open the 3D view.  The 3D view is checked
from the rendered pixels (red and green points drawn) and from the server-side scene (viser's
box handles equal the API's regions).  Views without auth are refused, over HTTP and websocket.
"""

from __future__ import annotations

import time
from typing import Any

import httpx
import numpy as np
import pytest
import viser

from tests.helpers.browser import (
    FAILING_SCAN_REASON,
    ReviewService,
    by_css,
    count_colour,
    dismiss_notifications,
    retry,
    save_screenshot,
    text_of,
    view_scene,
)
from tests.helpers.browser import wait_for_page as wait_until

pytestmark = pytest.mark.timeout(240)

RED = (230, 25, 25)
GREEN = (20, 200, 50)


def wait_for_view(driver: Any, service: ReviewService, job_id: str, clients: int = 1) -> bytes:
    """Wait until the browser's viser client connected and drew red and green points."""
    wait_until(
        lambda: len(view_scene(service, job_id).get("clients", [])) >= clients,
        90,
        "the 3D view's websocket did not connect to the job's viser server",
    )

    def drawn() -> bytes | None:
        png = driver.get_screenshot_as_png()
        return png if count_colour(png, RED) > 15 and count_colour(png, GREEN) > 15 else None

    return wait_until(drawn, 60, "no red and green points were drawn in the 3D view")


def assert_boxes_match_regions(scene: dict[str, Any], regions: list[dict[str, Any]]) -> None:
    """Every region has a box in viser's scene at its place and size (file coordinates)."""
    boxes = scene["clients"][0]["boxes"]
    assert len(boxes) == len(regions) > 0
    for box, region in zip(boxes, regions, strict=True):
        assert box["kind"] == region["kind"]
        assert box["visible"]
        expected_centre = (np.array(region["bbox_min"]) + np.array(region["bbox_max"])) / 2
        expected_size = np.maximum(
            np.array(region["bbox_max"]) - np.array(region["bbox_min"]), 0.01
        )
        assert np.allclose(box["center"], expected_centre, atol=1e-3)
        assert np.allclose(box["dimensions"], expected_size, atol=1e-3)


def assert_api_accepts_session_cookie(driver: Any, service: ReviewService) -> None:
    """The browser got an HttpOnly SameSite=Strict session cookie that the API accepts."""
    session_cookie = wait_until(
        lambda: driver.get_cookie("scandiff_session"), 10, "signing in set no session cookie"
    )
    assert session_cookie["httpOnly"] and session_cookie["sameSite"] == "Strict"
    sites = httpx.get(
        service.base_url + "/api/v1/sites",
        cookies={"scandiff_session": session_cookie["value"]},
    )
    assert sites.status_code == 200, (
        "the API does not accept the session cookie: app/api/deps.py must call "
        "app.api.session_auth.principal_from_session_cookie (see docs/review.md)"
    )


def test_review_with_the_mouse(review_service: ReviewService, chrome_factory) -> None:
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select

    service = review_service
    driver = chrome_factory()

    # Sign in: a wrong token is refused in words, the printed admin token works.
    driver.get(service.base_url + "/")
    by_css(driver, "#token").send_keys("sdt_not-a-real-token")
    assert not driver.find_element(By.ID, "sign-out").is_displayed()
    by_css(driver, "#sign-in-button").click()
    wait_until(lambda: "not valid" in text_of(driver, "#sign-in-error"), 10, "no refusal shown")
    token_field = by_css(driver, "#token")
    token_field.clear()
    token_field.send_keys(service.process.admin_token)
    by_css(driver, "#sign-in-button").click()
    assert_api_accepts_session_cookie(driver, service)
    by_css(driver, "#new-site-name").send_keys("Warehouse aisle B")

    # Create a site, upload its reference, then a scan (progress bar, then a live job).
    by_css(driver, "#create-site").click()
    assert by_css(driver, "#site-name").text == "Warehouse aisle B"
    by_css(driver, "#scan-file").send_keys(str(service.files.reference))
    by_css(driver, "#upload-reference").click()
    wait_until(
        lambda: "is now the reference" in text_of(driver, "#upload-status"), 60, "no reference"
    )
    assert driver.find_element(By.CSS_SELECTOR, "#upload-progress [role=progressbar]")
    wait_until(lambda: "points" in text_of(driver, ".facts"), 20, "reference not shown")
    by_css(driver, "#scan-file").send_keys(str(service.files.scan))
    by_css(driver, "#upload-scan").click()
    wait_until(lambda: "uploaded" in text_of(driver, "#upload-status"), 60, "no upload")
    wait_until(  # the upload card follows the job (queued, running, then done)
        lambda: driver.find_elements(By.CSS_SELECTOR, "#upload-job[data-job-status] a"),
        20,
        "no job",
    )
    wait_until(
        lambda: driver.find_elements(By.CSS_SELECTOR, "#jobs-table tbody tr"), 20, "no job row"
    )
    seen_statuses: set[str] = set()

    def job_succeeded() -> bool:
        rows = driver.find_elements(By.CSS_SELECTOR, "#jobs-table tbody tr")
        statuses = {row.get_attribute("data-status") for row in rows}
        seen_statuses.update(statuses)
        if "failed" in statuses:
            raise AssertionError(f"the job failed: {text_of(driver, '.error-cell')}")
        return statuses == {"succeeded"}

    wait_until(job_succeeded, 150, "the job did not succeed on the page (live updates)")
    wait_until(
        lambda: "Comparison done" in text_of(driver, "#upload-job"), 20, "the card's job is done"
    )
    assert seen_statuses & {"queued", "running"}, "the page never showed the job in progress"
    dot = by_css(driver, "#timeline circle.dot[data-job-id]")
    job_id = dot.get_attribute("data-job-id")
    assert driver.find_elements(By.CSS_SELECTOR, "#timeline .threshold-line")
    driver.set_window_size(1280, 1160)  # the whole site page in one picture
    save_screenshot(driver, "dashboard-site", docs_name="dashboard.png")
    driver.set_window_size(1280, 860)

    # Filters: "changed only" keeps this job iff the detector said changed.
    with service.client() as client:
        job = client.get(f"/api/v1/jobs/{job_id}").json()
        regions = client.get(f"/api/v1/jobs/{job_id}/regions", params={"limit": 1000}).json()[
            "items"
        ]
    service.made.update(job=job, regions=regions)
    retry(lambda: by_css(driver, "#filter-changed").click())
    wait_until(
        lambda: (
            by_css(driver, "#filter-changed").is_selected()
            and driver.find_elements(By.CSS_SELECTOR, "#jobs-table, #no-jobs")
        ),
        10,
        "the filter did not apply",
    )
    assert bool(driver.find_elements(By.CSS_SELECTOR, "#jobs-table tbody tr")) == job["changed"]
    retry(lambda: by_css(driver, "#filter-changed").click())
    retry(lambda: Select(by_css(driver, "#filter-status")).select_by_value("succeeded"))
    wait_until(
        lambda: (
            Select(by_css(driver, "#filter-status")).first_selected_option.text == "succeeded"
            and driver.find_elements(By.CSS_SELECTOR, "#jobs-table tbody tr[data-status=succeeded]")
        ),
        10,
        "the status filter did not apply",
    )

    # The job: numbers, regions, downloads.
    retry(
        lambda: driver.execute_script(
            "arguments[0].dispatchEvent(new MouseEvent('click'))",
            by_css(driver, "#timeline circle.dot[data-job-id]"),
        )
    )
    by_css(driver, "#job-numbers")
    if regions:  # the first page of the region table, in the job's order
        first_page = [r["kind"] for r in regions[:25]]
        wait_until(
            lambda: (
                [
                    row.get_attribute("data-kind")
                    for row in driver.find_elements(By.CSS_SELECTOR, "#regions-table tbody tr")
                ]
                == first_page
            ),
            10,
            f"the region table does not list {first_page}",
        )
    npz_href = by_css(driver, "#download-labels-npz").get_attribute("href")
    download = driver.execute_async_script(
        "const done = arguments[arguments.length - 1];"
        "fetch(arguments[0]).then(r => r.arrayBuffer().then(b => done([r.status, b.byteLength])))",
        npz_href,
    )
    assert download[0] == 200 and download[1] > 100
    save_screenshot(driver, "dashboard-job")

    # The 3D view opens in a new tab, connects through the proxy and draws the change.
    assert {r["kind"] for r in regions} >= {"added", "removed"}, regions
    by_css(driver, "#open-3d-view").click()
    wait_until(lambda: len(driver.window_handles) == 2, 10, "no new tab")
    driver.switch_to.window(driver.window_handles[1])
    assert driver.current_url.endswith(f"/jobs/{job_id}/view")
    png = wait_for_view(driver, service, job_id)
    dismiss_notifications(driver)
    time.sleep(1.0)  # let the labels and GUI settle for the picture
    save_screenshot(driver, "view-3d", docs_name="view-3d.png")
    assert count_colour(png, RED) > 15 and count_colour(png, GREEN) > 15
    scene = view_scene(service, job_id)
    assert_boxes_match_regions(scene, regions)
    layers = {layer["name"]: layer for layer in scene["scene"]["layers"]}
    assert layers["removed"]["shown"] > 0 and layers["added"]["shown"] > 0
    assert not scene["clients"][0]["layers"]["unobserved"]["visible"]
    # The region list moves the camera to the region clicked.
    target = regions[1]
    centre = (np.array(target["bbox_min"]) + np.array(target["bbox_max"])) / 2
    retry(
        lambda: driver.find_element(
            By.XPATH, "//button[starts-with(normalize-space(.), '#2 ')]"
        ).click()
    )
    wait_until(
        lambda: np.allclose(
            view_scene(service, job_id)["clients"][0]["camera"]["look_at"], centre, atol=1e-2
        ),
        20,
        "clicking region #2 did not move the camera to it",
    )
    driver.close()
    driver.switch_to.window(driver.window_handles[0])

    # A failed job is explained in words.
    driver.get(f"{service.base_url}/#/sites/{job['site_id']}")
    by_css(driver, "#scan-file").send_keys(str(service.files.failing_scan))
    by_css(driver, "#upload-scan").click()
    retry(lambda: Select(by_css(driver, "#filter-status")).select_by_value("failed"))
    wait_until(
        lambda: (
            FAILING_SCAN_REASON in text_of(driver, ".error-cell") or (driver.refresh() and False)
        ),
        60,
        "the failed job's reason is not shown",
    )
    by_css(driver, "#jobs-table tbody tr[data-status=failed] a.job-link").click()
    assert FAILING_SCAN_REASON in by_css(driver, "#job-error").text

    # Sign out: the dashboard and the view ask to sign in again.
    by_css(driver, "#sign-out").click()
    by_css(driver, "#sign-in-form")
    driver.get(f"{service.base_url}/jobs/{job_id}/view")
    assert "Sign in" in driver.find_element(By.TAG_NAME, "h1").text


def test_expired_session_is_explained(review_service: ReviewService, chrome_factory) -> None:
    from selenium.webdriver.common.by import By

    service = review_service
    token = service.create_token("Expiring Org", "reader")
    driver = chrome_factory()
    driver.get(service.base_url + "/")
    by_css(driver, "#token").send_keys(token)
    by_css(driver, "#sign-in-button").click()
    assert_api_accepts_session_cookie(driver, service)
    by_css(driver, "#no-sites")
    service.revoke_token(token)
    driver.refresh()
    banner = by_css(driver, "#banner")
    assert "token was revoked or the session expired" in banner.text
    assert driver.find_elements(By.CSS_SELECTOR, "#sign-in-form")


def test_view_refused_without_auth(review_service: ReviewService) -> None:
    import websockets.sync.client
    from websockets.exceptions import InvalidStatus

    service = review_service
    job = service.finished_job()
    view = f"{service.base_url}/jobs/{job['id']}/view"
    socket_url = view.replace("http://", "ws://")
    protocol = [f"viser-v{viser.__version__}"]

    # No cookie, no link: the page says why (401), a forged link is refused (403).
    plain = httpx.get(view)
    assert plain.status_code == 401 and "Sign in" in plain.text
    assert httpx.get(view, params={"link": "forged.link"}).status_code == 403
    # The websocket handshake is refused without a session or link cookie.
    with pytest.raises(InvalidStatus) as refused:
        websockets.sync.client.connect(socket_url, subprotocols=protocol, open_timeout=10)
    assert refused.value.response.status_code == 403
    # Another organisation's session sees nothing of this job.
    other = service.create_token("Other Org", "admin")
    with httpx.Client(base_url=service.base_url) as browser:
        assert browser.post("/api/v1/session", json={"token": other}).status_code == 200
        assert browser.get(f"/jobs/{job['id']}/view").status_code == 404
        assert browser.post(f"/api/v1/jobs/{job['id']}/view-link").status_code == 404
        cookie = f"scandiff_session={browser.cookies['scandiff_session']}"
    with pytest.raises(InvalidStatus):
        websockets.sync.client.connect(
            socket_url, subprotocols=protocol, additional_headers={"Cookie": cookie}
        )
    # The owner's session opens the view, but not from a page of another site (Origin).
    with httpx.Client(base_url=service.base_url) as browser:
        browser.post("/api/v1/session", json={"token": service.process.admin_token})
        own = f"scandiff_session={browser.cookies['scandiff_session']}"
        assert browser.get(f"/jobs/{job['id']}/view").status_code == 200
    with pytest.raises(InvalidStatus):
        websockets.sync.client.connect(
            socket_url,
            subprotocols=protocol,
            additional_headers={"Cookie": own},
            origin="http://evil.example",
        )
    with websockets.sync.client.connect(
        socket_url, subprotocols=protocol, additional_headers={"Cookie": own}, open_timeout=60
    ) as connection:
        assert connection.subprotocol == protocol[0]
        assert connection.recv(timeout=30)  # viser's first messages arrive through the proxy


@pytest.mark.slow  # a second software-WebGL render of the view; test_view_review_tools opens
# its view from a link in a fresh profile in make test, test_view_any_process checks the link
def test_view_link_opens_without_a_token(review_service: ReviewService, chrome_factory) -> None:
    service = review_service
    job = service.finished_job()
    with service.client() as client:
        answer = client.post(f"/api/v1/jobs/{job['id']}/view-link")
        assert answer.status_code == 200, answer.text
        url = answer.json()["url"]
    assert url.startswith(f"{service.base_url}/jobs/{job['id']}/view?link=")
    assert httpx.get(url).status_code == 200
    assert httpx.get(url.replace(job["id"], "0" * 32)).status_code in (401, 403)
    driver = chrome_factory()  # a fresh profile: no session cookie
    before = len(view_scene(service, job["id"]).get("clients", []))
    driver.get(url)
    png = wait_for_view(driver, service, job["id"], clients=before + 1)
    assert count_colour(png, RED) > 15
    assert_boxes_match_regions(view_scene(service, job["id"]), service.made["regions"])
