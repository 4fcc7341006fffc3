"""A job's uncertain regions reach a viewer's client over the wire (issue 29), no Chromium.

The real app (in-process uvicorn) serves the view of a job finished through the real
``store_results`` with one change and one uncertain region (evidence ``no_coverage``); a client
speaking viser's websocket protocol, with a session cookie, reports its camera as the browser
does.  Rules checked: viser sends the uncertain region as a grey dashed outline of its own
(``/uncertain/0``), apart from the change's solid box; the scene endpoint lists it under
``uncertain_regions`` (not among the regions) and the client's record holds its outline, visible
and grey.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import httpx
import numpy as np
import pytest
import websockets.sync.client

from app.core.pipeline import RegionSummary
from app.db.models import Scan
from app.db.session import transaction
from app.viewer.uncertain_display import UNCERTAIN_COLOUR
from tests.helpers.jobs import create_job, finish_job, load_job
from tests.helpers.server import ApiServer, fresh_api
from tests.helpers.viser_wire import VISER_SUBPROTOCOL, camera_message, receive_messages

pytestmark = pytest.mark.timeout(240)

UNCOVERED = RegionSummary(
    "removed", 40, [-1.0, 1.5, 1.0], [-1.05, 1.2, 0.6], [-0.95, 1.8, 1.4], 0.3, 0.5,
    evidence="no_coverage", confidence=0.5,
)  # fmt: skip
"""A patch of the corridor's wall the scan's path never reached."""


@pytest.fixture(scope="module")
def api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ApiServer]:
    """The app, its viewer included, on a fresh data directory."""
    yield from fresh_api(tmp_path_factory, "uncertain-view")


def line_segments(messages: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """The line segments among viser's messages: scene name -> props."""
    return {
        message["name"]: message["props"]
        for message in messages
        if message["type"] == "LineSegmentsMessage"
    }


def test_an_uncertain_region_is_sent_as_a_grey_dashed_outline_of_its_own(api: ApiServer) -> None:
    job_id = create_job(api.settings, n_points=3000)
    job = load_job(api.settings, job_id)
    with transaction(api.settings.sqlalchemy_url) as session:
        sizes = [
            session.get_one(Scan, scan_id).n_points
            for scan_id in (job.reference_scan_id, job.scan_id)
        ]
    finish_job(api, job_id, *sizes, uncertain_regions=[UNCOVERED])
    token = api.token("reader", organisation="tests")
    with httpx.Client(base_url=api.base_url, timeout=60) as browser:
        assert browser.post("/api/v1/session", json={"token": token}).status_code == 200
        cookie = f"scandiff_session={browser.cookies['scandiff_session']}"
        assert browser.get(f"/jobs/{job_id}/view").status_code == 200

    with websockets.sync.client.connect(
        f"{api.base_url.replace('http', 'ws', 1)}/jobs/{job_id}/view",
        subprotocols=[VISER_SUBPROTOCOL],  # type: ignore[list-item]
        additional_headers={"Cookie": cookie},
        origin=api.base_url,  # type: ignore[arg-type]
        open_timeout=60,
        max_size=None,
    ) as connection:
        connection.send(camera_message())
        messages = receive_messages(
            connection,
            lambda received: {"/uncertain/0", "/regions/0"} <= set(line_segments(received)),
            timeout=90,
        )
        record = httpx.get(
            f"{api.base_url}/api/v1/jobs/{job_id}/view/scene",
            headers={"Authorization": f"Bearer {token}"},
            timeout=30,
        ).json()

    outlines = line_segments(messages)
    dashed = np.asarray(outlines["/uncertain/0"]["points"], dtype=np.float32).reshape(-1, 2, 3)
    solid = np.asarray(outlines["/regions/0"]["points"], dtype=np.float32).reshape(-1, 2, 3)
    assert len(solid) == 12 and len(dashed) > 12  # the change solid, the uncertain one dashed
    colours = np.asarray(outlines["/uncertain/0"]["colors"]).reshape(-1, 3)
    assert {tuple(int(value) for value in colour) for colour in colours} == {UNCERTAIN_COLOUR}
    scene = record["scene"]
    assert [region["kind"] for region in scene["regions"]] == ["added"]
    (listed,) = scene["uncertain_regions"]
    assert listed["evidence"] == "no_coverage" and listed["n_points"] == UNCOVERED.n_points
    (client,) = record["clients"]
    (drawn,) = client["uncertain"]
    assert drawn["visible"] and drawn["evidence"] == "no_coverage"
    assert drawn["colour"] == list(UNCERTAIN_COLOUR)
    np.testing.assert_allclose(drawn["bbox_min"], UNCOVERED.bbox_min, atol=1e-4)
    np.testing.assert_allclose(drawn["bbox_max"], UNCOVERED.bbox_max, atol=1e-4)
    assert client["controls"]["uncertain_regions"] is True
