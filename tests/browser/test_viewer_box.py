"""The 3D view's "Full density in a box" panel driven in a real headless Chromium, checked on
viser's server-side scene (``/api/v1/jobs/{id}/view/scene``).

Loading the box offered (the regions' box grown by a metre) draws exactly the job's points
inside it, says so in the panel, and "Back to the whole view" draws the whole view again.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from app.core.formats import read_point_cloud
from app.core.registration import apply_transform
from app.viewer.box_controls import BOX_MARGIN
from tests.helpers.browser import ReviewService, view_scene
from tests.helpers.browser import wait_for_page as wait_until

pytestmark = pytest.mark.timeout(300)


def client_scene(service: ReviewService, job_id: str) -> dict[str, Any]:
    """What viser holds for the one browser of the test."""
    clients = view_scene(service, job_id).get("clients", [])
    assert len(clients) == 1, clients
    return clients[0]


def drawn_points(scene: dict[str, Any]) -> int:
    """Points drawn over the visible layers' nodes and hidden ones alike."""
    return sum(layer["n_points"] for layer in scene["layers"].values())


def click_text(driver: Any, text: str) -> None:
    """Click the displayed element whose own text is ``text`` (a button, a folder's title)."""
    from selenium.webdriver.common.by import By

    wait_until(
        lambda: next(
            (
                element
                for element in driver.find_elements(
                    By.XPATH, f"//*[normalize-space(text())='{text}']"
                )
                if element.is_displayed()
            ),
            None,
        ),
        20,
        f"nothing reads {text!r}",
    ).click()


def test_a_box_at_full_density_and_back(review_service: ReviewService, chrome_factory) -> None:
    service = review_service
    job = service.finished_job()
    job_id = job["id"]
    with service.client() as client:
        url = client.post(f"/api/v1/jobs/{job_id}/view-link").json()["url"]
        details = client.get(f"/api/v1/jobs/{job_id}").json()
    driver = chrome_factory()
    driver.get(url)
    whole = wait_until(
        lambda: (
            (clients := view_scene(service, job_id).get("clients"))
            and drawn_points(clients[0])
            and clients[0]
        ),
        90,
        "the view did not draw",
    )
    assert "box_low" in whole["controls"]

    click_text(driver, "Full density in a box")
    click_text(driver, "Load the box at full density")
    status = wait_until(
        lambda: (
            "at full density" in (s := client_scene(service, job_id))["controls"]["box_status"]
            and s
        ),
        60,
        "the box was not loaded",
    )
    low = np.asarray(status["controls"]["box_low"])
    high = np.asarray(status["controls"]["box_high"])
    regions = details["regions"]
    np.testing.assert_allclose(low, np.min([r["bbox_min"] for r in regions], axis=0) - BOX_MARGIN)
    reference = read_point_cloud(service.files.reference).points
    transform = np.asarray(details["registration"]["transform"])
    scan = apply_transform(read_point_cloud(service.files.scan).points, transform)
    inside = sum(
        int(((points >= low) & (points <= high)).all(axis=1).sum()) for points in (reference, scan)
    )
    assert drawn_points(status) == inside < drawn_points(whole)
    assert f"{inside:,}" in status["controls"]["box_status"]

    click_text(driver, "Back to the whole view")
    wait_until(
        lambda: drawn_points(client_scene(service, job_id)) == drawn_points(whole),
        60,
        "the whole view was not drawn again",
    )
