"""No port serves scan data without the token: the viser servers behind the 3D view check a
per-view secret that only their API process's proxy presents (app/viewer/viser_guard.py).

A raw websocket to a viewer's loopback port, with viser's subprotocol and the camera message a
browser sends, is closed (1008) before it receives a single message; the same connection with
the secret gets the scene.  Against the real service, every TCP port its processes listen on
besides the API's is tried the same way while a proxied view is open and receiving.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from types import SimpleNamespace
from typing import Any

import httpx
import numpy as np
import pytest
import viser
import websockets.exceptions
import websockets.sync.client

from app.core.datasets.scenes import raycast_scene
from app.viewer.manager import JobViewer, ViewerManager
from app.viewer.scene import build_scene_data
from app.viewer.viser_guard import (
    VIEW_SECRET_HEADER,
    ViserInternalsChangedError,
    require_view_secret,
)
from tests.helpers.browser import ReviewService, listening_tcp_ports
from tests.helpers.viser_wire import (
    VISER_SUBPROTOCOL,
    camera_message,
    decode_frame,
    point_clouds,
    receive_messages,
)

pytestmark = pytest.mark.timeout(240)


def connect(port: int, headers: dict[str, str] | None = None, path: str = "") -> Any:
    """A ``websockets`` client connection to 127.0.0.1:``port`` with viser's subprotocol."""
    return websockets.sync.client.connect(
        f"ws://127.0.0.1:{port}{path}",
        subprotocols=[VISER_SUBPROTOCOL],  # type: ignore[list-item]
        additional_headers=headers or {},
        open_timeout=30,
        max_size=None,
    )


def frames_before_close(connection: Any, timeout: float = 15.0) -> tuple[list[bytes], int | None]:
    """Every frame received until the server closes (after sending the camera message), and
    the close code; fails if the connection is still open after ``timeout``."""
    frames = []
    with contextlib.suppress(websockets.exceptions.ConnectionClosed):
        connection.send(camera_message())
    try:
        while True:
            frames.append(connection.recv(timeout=timeout))
    except websockets.exceptions.ConnectionClosed as closed:
        return frames, closed.rcvd.code if closed.rcvd else None
    except TimeoutError:
        pytest.fail(f"the connection stayed open for {timeout}s after {len(frames)} frames")


def layer_clouds(connection: Any, count: int) -> dict[str, np.ndarray]:
    """The first ``count`` layer point clouds viser sends after the camera message."""
    connection.send(camera_message())
    messages = receive_messages(
        connection,
        lambda received: (
            len([n for n in point_clouds(received) if n.startswith("/layers/")]) >= count
        ),
    )
    return point_clouds(messages)


@pytest.fixture(scope="module")
def viewer() -> Iterator[tuple[ViewerManager, JobViewer]]:
    """A running viewer of a small synthetic scene."""
    pair = raycast_scene(n_points=3000, change="mixed", pose_error=(0.05, 1.0), random_state=3)
    data = build_scene_data(pair.reference[:500], pair.scan[:500])
    manager = ViewerManager(lambda job_id: (data, f"job {job_id}"), idle_seconds=60)
    try:
        yield manager, manager.get("a")
    finally:
        manager.stop_all()


@pytest.mark.parametrize("secret", [None, "", "a-guessed-secret"], ids=["none", "empty", "wrong"])
def test_a_raw_websocket_to_a_viewer_port_without_its_secret_gets_nothing(
    viewer: tuple[ViewerManager, JobViewer], secret: str | None, recwarn: pytest.WarningsRecorder
) -> None:
    _, job_viewer = viewer
    headers = None if secret is None else {VIEW_SECRET_HEADER: secret}
    with connect(job_viewer.port, headers) as connection:
        frames, code = frames_before_close(connection)
    assert frames == []
    assert code == 1008
    # Its camera message (buffered before the close) built no scene for it either.
    assert job_viewer.clients == {}
    assert not [w for w in recwarn if "closed connection" in str(w.message)]


def test_the_same_websocket_with_the_secret_gets_the_scene(
    viewer: tuple[ViewerManager, JobViewer],
) -> None:
    manager, job_viewer = viewer
    with connect(job_viewer.port, {VIEW_SECRET_HEADER: job_viewer.secret}) as connection:
        clouds = layer_clouds(connection, len(job_viewer.data.layers))
    for layer in job_viewer.data.layers:
        if layer.n_shown:
            assert np.array_equal(clouds[f"/layers/{layer.name}"], layer.points)
    assert manager.get("b").secret != job_viewer.secret  # one secret per view


def test_connections_opened_before_the_check_are_closed_before_any_scene() -> None:
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        with connect(server.get_port()) as early:
            early.send(camera_message())
            require_view_secret(server, "the-secret")
            server.scene.add_point_cloud(
                "/layers/secret", points=np.ones((10, 3), np.float32), colors=(255, 0, 0)
            )
            frames, code = frames_before_close(early)
        assert code == 1008
        assert not any(
            message["type"] == "PointCloudMessage"
            for frame in frames
            for message in decode_frame(frame)
        )
    finally:
        server.stop()


def test_the_adapter_fails_loudly_when_viser_changes() -> None:
    with pytest.raises(ViserInternalsChangedError, match="viser_guard"):
        require_view_secret(SimpleNamespace(_websock_server=None), "s")  # type: ignore[arg-type]
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        websock = server._websock_server
        live = websock._live_connections
        del websock._live_connections
        try:
            with pytest.raises(ViserInternalsChangedError):
                require_view_secret(server, "s")
        finally:
            websock._live_connections = live
        with pytest.raises(ValueError):
            require_view_secret(server, "")
    finally:
        server.stop()


def test_no_port_of_the_service_serves_a_view_without_the_session(
    review_service: ReviewService,
) -> None:
    service = review_service
    job = service.finished_job()
    with httpx.Client(base_url=service.base_url) as browser:
        browser.post("/api/v1/session", json={"token": service.process.admin_token})
        cookie = f"scandiff_session={browser.cookies['scandiff_session']}"
    # A proxied view is open and receiving while every other port is tried.
    with connect(
        service.process.port, {"Cookie": cookie}, path=f"/jobs/{job['id']}/view"
    ) as proxied:
        assert layer_clouds(proxied, 5)
        ports = listening_tcp_ports(service.process.pid) - {service.process.port}
        assert ports, "the job's viser server should be listening while its view is open"
        for port in sorted(ports):
            try:
                with connect(port) as raw:
                    frames, code = frames_before_close(raw)
            except (OSError, websockets.exceptions.InvalidHandshake):
                continue  # not a websocket server, or refused at the handshake: nothing served
            assert frames == [], f"port {port} sent {len(frames)} frames without the secret"
            assert code == 1008
    # The proxied view still works after the raw attempts (a fresh connection gets the scene).
    with connect(
        service.process.port, {"Cookie": cookie}, path=f"/jobs/{job['id']}/view"
    ) as proxied:
        assert layer_clouds(proxied, 5)
