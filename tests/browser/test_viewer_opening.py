"""The 3D view opens on the change (issue 31): a job opened in headless Chromium (software
WebGL, 1280 x 800) shows at least 200 change-coloured pixels in its first frame, indoors with
the change behind a wall and outdoors on a real street frame; the server-side record says the
camera looks at the change.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pytest

from app.core.datasets.lidar import lidar_pair
from app.testing.files import pcd_bytes
from app.viewer.colours import ADDED_COLOUR, REMOVED_COLOUR
from app.viewer.regions_display import CameraView, label_box
from tests.helpers.browser import (
    ReviewService,
    count_colour,
    dismiss_notifications,
    save_screenshot,
    view_scene,
)
from tests.helpers.browser import wait_for_page as wait_until
from tests.helpers.http import create_site, unique_name, upload
from tests.helpers.street import street_with_a_parked_car

pytestmark = pytest.mark.timeout(600)

MIN_CHANGE_PIXELS = 200
WINDOW = (1280, 800)


def compared_job(service: ReviewService, name: str, reference: bytes, scan: bytes) -> str:
    """Upload a reference and a scan to a new site; the id of their finished job."""
    with service.client() as client:
        site = create_site(client, unique_name(name))
        answer = upload(client, site["id"], reference, filename="reference.pcd", reference=True)
        assert answer.status_code == 201, answer.text
        answer = upload(client, site["id"], scan, filename="scan.pcd")
        assert answer.status_code == 202, answer.text
        job = service.process.wait_for_job(client, answer.json()["job"]["id"], timeout=400)
        assert job["status"] == "succeeded", job
        assert job["changed"], job
        return str(job["id"])


def set_viewport(driver: Any, width: int, height: int) -> None:
    """Make the page's viewport ``width`` x ``height`` pixels (a headless window is no larger
    than its virtual screen, so through DevTools' device metrics)."""
    driver.execute_cdp_cmd(
        "Emulation.setDeviceMetricsOverride",
        {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False},
    )


PANELS_SCRIPT = """
const rects = [];
const legend = document.querySelector('.scandiff-legend');
if (legend) {  // viser's control panel: the widest ancestor of the legend narrower than 700 px
  let panel = legend;
  for (let node = legend; node && node !== document.body; node = node.parentElement) {
    if (node.getBoundingClientRect().width < 700) panel = node;
  }
  rects.push(panel.getBoundingClientRect());
}
const review = document.getElementById('view-review');
if (review) rects.push(review.getBoundingClientRect());
return rects.map(r => [r.left, r.top, r.right, r.bottom]);
"""


def scene_pixels(driver: Any) -> bytes:
    """A screenshot with the GUI panels (their legend swatches are red and green) blanked."""
    import io

    from PIL import Image, ImageDraw

    rectangles = driver.execute_script(PANELS_SCRIPT)
    image = Image.open(io.BytesIO(driver.get_screenshot_as_png())).convert("RGB")
    drawing = ImageDraw.Draw(image)
    for left, top, right, bottom in rectangles:
        drawing.rectangle((left, top, right, bottom), fill=(255, 255, 255))
    stream = io.BytesIO()
    image.save(stream, format="PNG")
    return stream.getvalue()


def first_frame_change_pixels(
    service: ReviewService, job_id: str, driver: Any, name: str
) -> tuple[int, dict[str, Any]]:
    """Open the job's 3D view at 1280 x 800 and count removed- and added-coloured pixels once
    the scene is drawn, without touching the camera; that count and the view's record."""
    from selenium.common.exceptions import TimeoutException

    with service.client() as client:
        url = client.post(f"/api/v1/jobs/{job_id}/view-link").json()["url"]
    set_viewport(driver, *WINDOW)
    driver.get(url)
    inner = driver.execute_script("return [window.innerWidth, window.innerHeight]")
    assert tuple(inner) == WINDOW, inner
    wait_until(
        lambda: (
            (scene := view_scene(service, job_id)).get("clients")
            and scene["clients"][0]["camera"]["image_size"][1] > 0
            and scene["clients"][0]["layers"]
            and scene
        ),
        180,
        "the 3D view did not connect and draw its layers",
    )
    best = 0
    # software WebGL: the first frames may take a while, and longer beside a running suite
    # (30 s saw every capture time out under `make test` + `make test-slow`)
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline and best < MIN_CHANGE_PIXELS:
        dismiss_notifications(driver)
        try:
            png = scene_pixels(driver)
        except TimeoutException:  # a loaded machine's software renderer: try the next frame
            continue
        best = max(best, count_colour(png, REMOVED_COLOUR) + count_colour(png, ADDED_COLOUR))
        time.sleep(1.0)
    for attempt in range(3):  # the artifact only: a busy software renderer may miss a capture
        try:
            save_screenshot(driver, name, docs_name=f"{name}.png")
            break
        except TimeoutException:
            if attempt == 2:  # the change pixels above are the check, not the artifact
                print(f"{name}: no artifact screenshot, the renderer timed out 3 times")
    print(f"{name}: {best} change pixels in the first frame")
    driver.execute_cdp_cmd("Emulation.clearDeviceMetricsOverride", {})
    return best, view_scene(service, job_id)


def assert_labels_apart(record: dict[str, Any]) -> None:
    """Every sensor keeps its label, and no two shown labels overlap on the browser's screen."""
    client = record["clients"][0]
    camera = client["camera"]
    view = CameraView(
        position=np.asarray(camera["position"]),
        wxyz=np.asarray(camera["wxyz"]),
        fov=camera["fov"],
        width=camera["image_size"][0],
        height=camera["image_size"][1],
    )
    sensors = [label for label in client["labels"] if label["kind"] == "sensor"]
    assert len(sensors) == 2 and all(label["visible"] for label in sensors), sensors
    shown = [label for label in client["labels"] if label["visible"]]
    pixels, _ = view.project(np.array([label["position"] for label in shown]))
    boxes = [
        label_box(pixel, label["text"], label["anchor"])
        for pixel, label in zip(pixels, shown, strict=True)
    ]
    for index, box in enumerate(boxes):
        for other in boxes[:index]:
            assert not (
                box[0] < other[2] and other[0] < box[2] and box[1] < other[3] and other[1] < box[3]
            ), shown


def assert_looks_at_the_change(record: dict[str, Any]) -> None:
    """The opening camera looks at the regions' box, which it does not see through walls."""
    opening = record["scene"]["opening"]
    regions = record["scene"]["regions"]
    low = np.min([region["bbox_min"] for region in regions], axis=0)
    high = np.max([region["bbox_max"] for region in regions], axis=0)
    assert np.all(np.asarray(opening["look_at"]) >= low - 1e-6), (opening, low)
    assert np.all(np.asarray(opening["look_at"]) <= high + 1e-6), (opening, high)
    assert opening["reason"].startswith("change")
    assert opening["blocked_share"] <= 0.4
    camera = record["clients"][0]["camera"]
    assert np.allclose(camera["look_at"], opening["look_at"], atol=1e-3)


def test_an_indoor_change_behind_a_wall_is_seen_at_once(
    review_service: ReviewService, chrome_factory
) -> None:
    # a warehouse whose removed pallet stands behind a rack, seen from the whole-scene view's side
    pair = lidar_pair(
        layout="warehouse", change="removed", angular_step_deg=(2.0, 1.0), random_state=2
    )
    reference = pcd_bytes(pair.reference, viewpoint=(*pair.reference_origin, 1, 0, 0, 0))
    scan = pcd_bytes(pair.scan, viewpoint=(*pair.scan_origin, 1, 0, 0, 0))
    job_id = compared_job(review_service, "indoor-behind-wall", reference, scan)
    pixels, record = first_frame_change_pixels(
        review_service, job_id, chrome_factory(), "view-opening-indoor"
    )
    assert pixels >= MIN_CHANGE_PIXELS, f"{pixels} change pixels in the first frame"
    assert_looks_at_the_change(record)
    assert_labels_apart(record)


@pytest.mark.slow  # a comparison of a 120k-point real frame, then its software-WebGL render;
# make test keeps the indoor opening above (the change behind a wall, a synthetic warehouse)
def test_an_outdoor_street_change_is_seen_at_once(
    review_service: ReviewService, chrome_factory
) -> None:
    reference_points, scan_points = street_with_a_parked_car()
    viewpoint = (0, 0, 0, 1, 0, 0, 0)  # KITTI frames are in their sensor's frame
    job_id = compared_job(
        review_service,
        "street-parked-car",
        pcd_bytes(reference_points, viewpoint=viewpoint),
        pcd_bytes(scan_points, viewpoint=viewpoint),
    )
    pixels, record = first_frame_change_pixels(
        review_service, job_id, chrome_factory(), "view-opening-street"
    )
    assert pixels >= MIN_CHANGE_PIXELS, f"{pixels} change pixels in the first frame"
    assert_looks_at_the_change(record)
    assert_labels_apart(record)
