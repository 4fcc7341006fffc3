"""A 3D view opened through one API process works when its websocket lands on another.

Two real API processes (``uvicorn --factory app.main:create_app``) share one data directory and
one SQLite database, as API replicas behind a load balancer without sticky sessions share them.
A finished job is made through the real ``store_results``.  The view page is opened through one
process (with a session cookie, or a view link, obtained through it) and the websocket goes to
the other: that process starts its own viser server for the job and sends the scene, which is
the same scene the first process built.

Behind a load balancer both processes have one origin; here each has its own port, so the
websocket's ``Origin`` names the process it connects to, as the balancer's would.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import httpx
import numpy as np
import pytest
import websockets.sync.client

from app.config import Settings
from app.db.migrate import upgrade_to_head
from app.db.models import Scan
from app.db.session import transaction
from app.testing.service import ApiProcess
from app.testing.waiting import wait_until
from app.viewer.access import VIEW_COOKIE
from tests.helpers.jobs import create_job, finish_job, load_job
from tests.helpers.server import ApiServer
from tests.helpers.viser_wire import (
    VISER_SUBPROTOCOL,
    camera_message,
    point_clouds,
    receive_messages,
)

pytestmark = pytest.mark.timeout(240)


@dataclass
class TwoApis:
    """Two API processes on one data directory, finished jobs (one per test) and a token."""

    first: ApiProcess
    second: ApiProcess
    job_ids: list[str]
    token: str

    def for_test(self, index: int) -> tuple[ApiProcess, ApiProcess, str, str]:
        """Both processes, the test's own job (no viewer of it runs yet) and the token."""
        return self.first, self.second, self.job_ids[index], self.token


@pytest.fixture(scope="module")
def two_apis(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TwoApis]:
    """Two API processes sharing one migrated data directory, with a succeeded job in it."""
    root = tmp_path_factory.mktemp("two-apis")
    settings = Settings(data_dir=root / "data")
    settings.data_dir.mkdir()
    upgrade_to_head(settings.sqlalchemy_url)
    handle = ApiServer(settings=settings, base_url="")
    job_ids = [create_job(settings, n_points=3000) for _ in range(3)]
    for job_id in job_ids:
        job = load_job(settings, job_id)
        with transaction(settings.sqlalchemy_url) as session:
            sizes = [
                session.get_one(Scan, scan_id).n_points
                for scan_id in (job.reference_scan_id, job.scan_id)
            ]
        finish_job(handle, job_id, *sizes)
    token = handle.token("reader", organisation="tests")  # create_job's organisation
    first = ApiProcess(settings.data_dir, log_path=root / "first.log")
    second = ApiProcess(settings.data_dir, log_path=root / "second.log")
    try:
        first.start()
        second.start()
        yield TwoApis(first, second, job_ids, token)
    finally:
        for process in (first, second):
            process.stop(timeout=20)


def view_record(api: ApiProcess, token: str, job_id: str) -> dict[str, Any]:
    """What ``api``'s own viewer of the job holds (``running: False`` when it has none)."""
    answer = httpx.get(
        f"{api.base_url}/api/v1/jobs/{job_id}/view/scene",
        headers={"Authorization": f"Bearer {token}"},
        timeout=30,
    )
    answer.raise_for_status()
    return answer.json()


def running_view(api: ApiProcess, token: str, job_id: str) -> dict[str, Any]:
    """``api``'s viewer record of the job once it runs (the view page starts it)."""
    return wait_until(
        lambda: (record := view_record(api, token, job_id)).get("running") and record,
        60,
        f"{api.base_url} did not start the job's viewer for its page",
    )


def shown_counts(record: dict[str, Any]) -> dict[str, int]:
    """Points shown per layer in a view record."""
    return {layer["name"]: layer["shown"] for layer in record["scene"]["layers"]}


def scene_through(api: ApiProcess, job_id: str, cookie: str) -> dict[str, np.ndarray]:
    """The layers' point clouds viser sends through ``api``'s websocket proxy to a client that
    presents ``cookie`` and reports its camera (as the browser does)."""
    url = f"ws://127.0.0.1:{api.port}/jobs/{job_id}/view"
    with websockets.sync.client.connect(
        url,
        subprotocols=[VISER_SUBPROTOCOL],  # type: ignore[list-item]
        additional_headers={"Cookie": cookie},
        origin=api.base_url,  # type: ignore[arg-type]
        open_timeout=60,
        max_size=None,
    ) as connection:
        assert connection.subprotocol == VISER_SUBPROTOCOL
        connection.send(camera_message())
        messages = receive_messages(
            connection,
            lambda received: (
                len([name for name in point_clouds(received) if name.startswith("/layers/")]) >= 5
            ),
            timeout=90,
        )
    return {
        name.removeprefix("/layers/"): points
        for name, points in point_clouds(messages).items()
        if name.startswith("/layers/")
    }


def assert_same_scene(
    received: dict[str, np.ndarray], served: dict[str, Any], opened: dict[str, Any]
) -> None:
    """The client got every layer the serving process holds, every changed point it shows (the
    rest at most as many as it shows: an indoor view opens cut below its ceiling, never below a
    change), and the process that opened the page built the same scene."""
    counts = shown_counts(served)
    assert set(received) == set(counts)
    for name, shown in counts.items():
        if not shown:  # an empty layer is sent as one hidden placeholder point
            continue
        if name in ("added", "removed"):
            assert len(received[name]) == shown, name
        else:
            assert 0 < len(received[name]) <= shown, name
    assert sum(counts.values()) > 0 and counts["added"] > 0 and counts["removed"] > 0
    assert shown_counts(opened) == counts
    assert opened["scene"]["origin"] == served["scene"]["origin"]


def test_a_view_opened_through_one_process_is_served_by_the_other(two_apis: TwoApis) -> None:
    first, second, job_id, token = two_apis.for_test(0)
    # A session cookie from the first process; the view page through the first process.
    with httpx.Client(base_url=first.base_url, timeout=60) as browser:
        assert browser.post("/api/v1/session", json={"token": token}).status_code == 200
        session_cookie = f"scandiff_session={browser.cookies['scandiff_session']}"
        assert browser.get(f"/jobs/{job_id}/view").status_code == 200
    opened = running_view(first, token, job_id)
    before = view_record(second, token, job_id)
    # The websocket lands on the second process: it serves the scene with its own viser server.
    received = scene_through(second, job_id, session_cookie)
    served = view_record(second, token, job_id)
    assert served["running"] and not before.get("connections")
    assert_same_scene(received, served, opened)
    assert view_record(first, token, job_id)["connections"] == 0  # the first one served nothing


def test_a_view_link_made_through_one_process_opens_through_the_other(two_apis: TwoApis) -> None:
    first, second, job_id, token = two_apis.for_test(1)
    made = httpx.post(
        f"{second.base_url}/api/v1/jobs/{job_id}/view-link",
        headers={"Authorization": f"Bearer {token}"},
        timeout=30,
    )
    assert made.status_code == 200, made.text
    # The page opened through the second process (no session: the link alone).
    page = httpx.get(made.json()["url"], timeout=60)
    assert page.status_code == 200
    link_cookie = f"{VIEW_COOKIE}={page.cookies[VIEW_COOKIE]}"
    opened = running_view(second, token, job_id)
    # The websocket, with the link's cookie only, lands on the first process.
    connections_before = view_record(first, token, job_id).get("connections", 0)
    received = scene_through(first, job_id, link_cookie)
    served = view_record(first, token, job_id)
    assert served["running"]
    assert_same_scene(received, served, opened)
    assert view_record(second, token, job_id)["connections"] == 0
    assert connections_before == 0


def test_the_other_process_refuses_a_websocket_without_session_or_link(two_apis: TwoApis) -> None:
    from websockets.exceptions import InvalidStatus

    url = f"ws://127.0.0.1:{two_apis.second.port}/jobs/{two_apis.job_ids[2]}/view"
    with pytest.raises(InvalidStatus) as refused:
        websockets.sync.client.connect(
            url,
            subprotocols=[VISER_SUBPROTOCOL],
            open_timeout=30,  # type: ignore[list-item]
        )
    assert refused.value.response.status_code == 403
