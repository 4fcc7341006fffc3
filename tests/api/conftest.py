"""Fixtures for API tests: the real app served by uvicorn over HTTP on a migrated SQLite file.

``api`` is one server per test module (a background thread running uvicorn on a free port with
``create_app(Settings(data_dir=...))`` after ``upgrade_to_head``); tests isolate themselves by
creating their own organisations and tokens (``api.token(...)``).  No job consumer runs here:
jobs stay ``queued`` unless a test plays the worker (``api.finish_job``); the whole flow with a
real consumer is in ``test_service_flow.py``.
"""

from __future__ import annotations

import io
import socket
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import laspy
import numpy as np
import pypcd4
import pytest
import uvicorn
from numpy.typing import NDArray
from plyfile import PlyData, PlyElement

from app.config import Settings
from app.db.migrate import upgrade_to_head
from app.db.session import transaction
from app.main import create_app
from app.services.auth import create_token

MAX_UPLOAD_BYTES = 400_000
"""Upload cap of the test server (a 5k-point binary PLY is ~60 kB; 413 tests send more)."""


# -- clouds and files -----------------------------------------------------------------------------


def make_points(n_points: int = 3000, seed: int = 0) -> NDArray[np.float64]:
    """A small room-like cloud: a floor and two walls with a little noise (metres)."""
    rng = np.random.default_rng(seed)
    third = n_points // 3
    floor = np.column_stack(
        [rng.uniform(0, 6, third), rng.uniform(0, 4, third), rng.normal(0, 0.005, third)]
    )
    wall_x = np.column_stack(
        [rng.uniform(0, 6, third), rng.normal(4, 0.005, third), rng.uniform(0, 2.5, third)]
    )
    rest = n_points - 2 * third
    wall_y = np.column_stack(
        [rng.normal(0, 0.005, rest), rng.uniform(0, 4, rest), rng.uniform(0, 2.5, rest)]
    )
    return np.vstack([floor, wall_x, wall_y])


def ply_bytes(points: NDArray[np.float64], text: bool = False) -> bytes:
    """A PLY file (binary little endian unless ``text``) with float32 x, y, z."""
    vertex = np.empty(len(points), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    vertex["x"], vertex["y"], vertex["z"] = points.T
    buffer = io.BytesIO()
    PlyData([PlyElement.describe(vertex, "vertex")], text=text).write(buffer)
    return buffer.getvalue()


def pcd_bytes(points: NDArray[np.float64]) -> bytes:
    """A binary PCD file."""
    buffer = io.BytesIO()
    pypcd4.PointCloud.from_xyz_points(points.astype(np.float32)).save(buffer)
    return buffer.getvalue()


def las_bytes(points: NDArray[np.float64], compressed: bool = True) -> bytes:
    """A LAZ (or LAS) file at millimetre resolution."""
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = points.min(axis=0)
    las = laspy.LasData(header)
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    buffer = io.BytesIO()
    las.write(buffer, do_compress=compressed)
    return buffer.getvalue()


def unique_name(prefix: str) -> str:
    """A name no other test (or earlier run on a persistent database) used."""
    return f"{prefix}-{uuid.uuid4().hex[:12]}"


# -- the server ----------------------------------------------------------------------------------


def free_port() -> int:
    """A TCP port that was free a moment ago."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@dataclass
class ApiServer:
    """A running app and handles on its data."""

    settings: Settings
    base_url: str
    clients: list[httpx.Client] = field(default_factory=list)

    @property
    def data_dir(self) -> Path:
        return self.settings.data_dir

    def token(self, role: str = "writer", organisation: str | None = None) -> str:
        """A new token for ``organisation`` (default: a fresh one)."""
        with transaction(self.settings.sqlalchemy_url) as session:
            return create_token(session, organisation or unique_name("org"), role)

    def client(self, token: str | None = None, **kwargs: Any) -> httpx.Client:
        """An HTTP client on the server, authenticated with ``token`` when given."""
        headers = dict(kwargs.pop("headers", {}))
        if token:
            headers["Authorization"] = f"Bearer {token}"
        client = httpx.Client(base_url=self.base_url, headers=headers, timeout=30.0, **kwargs)
        self.clients.append(client)
        return client

    def stored_files(self) -> list[Path]:
        """Every file under scans/ and tmp/ (what uploads leave behind)."""
        return sorted(
            path
            for directory in (self.settings.scans_dir, self.settings.tmp_dir)
            for path in directory.rglob("*")
            if path.is_file()
        )


def start_server(settings: Settings) -> tuple[uvicorn.Server, threading.Thread, str]:
    """Migrate, then run uvicorn with ``create_app(settings)`` in a thread; wait until it serves."""
    upgrade_to_head(settings.sqlalchemy_url)
    port = free_port()
    config = uvicorn.Config(
        create_app(settings), host="127.0.0.1", port=port, log_level="warning", lifespan="off"
    )
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 20
    while not server.started:
        if time.monotonic() > deadline or not thread.is_alive():
            raise RuntimeError("test server did not start")
        time.sleep(0.02)
    return server, thread, f"http://127.0.0.1:{port}"


@contextmanager
def running_api(settings: Settings) -> Iterator[ApiServer]:
    """The app served by uvicorn in a thread for ``settings``; stopped on exit."""
    server, thread, base_url = start_server(settings)
    handle = ApiServer(settings=settings, base_url=base_url)
    try:
        yield handle
    finally:
        for client in handle.clients:
            client.close()
        server.should_exit = True
        thread.join(timeout=10)


@pytest.fixture(scope="module")
def api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ApiServer]:
    """The app on a fresh, migrated data directory, for one test module."""
    settings = Settings(
        data_dir=tmp_path_factory.mktemp("api-data"),
        max_upload_bytes=MAX_UPLOAD_BYTES,
    )
    with running_api(settings) as handle:
        yield handle


@pytest.fixture
def writer(api: ApiServer) -> httpx.Client:
    """A writer of a fresh organisation."""
    return api.client(api.token("writer"))


def create_site(client: httpx.Client, name: str | None = None, **fields: Any) -> dict[str, Any]:
    """POST a site and return it (asserting 201)."""
    response = client.post(
        "/api/v1/sites", json={"name": name or f"site-{uuid.uuid4().hex[:6]}", **fields}
    )
    assert response.status_code == 201, response.text
    return response.json()


def upload(
    client: httpx.Client,
    site_id: str,
    content: bytes,
    *,
    filename: str | None = "scan.ply",
    reference: bool = False,
    multipart: bool = False,
    headers: dict[str, str] | None = None,
    **params: Any,
) -> httpx.Response:
    """Upload a scan as the raw body (default) or as the multipart field ``file``."""
    query: dict[str, Any] = {"reference": str(reference).lower(), **params}
    if multipart:
        return client.post(
            f"/api/v1/sites/{site_id}/scans",
            params=query,
            files={"file": (filename or "blob", content, "application/octet-stream")},
            headers=headers,
        )
    if filename is not None:
        query["filename"] = filename
    return client.post(
        f"/api/v1/sites/{site_id}/scans",
        params=query,
        content=content,
        headers={"Content-Type": "application/octet-stream", **(headers or {})},
    )


def site_with_reference(client: httpx.Client) -> tuple[dict[str, Any], dict[str, Any]]:
    """A new site whose reference is a 3k-point PLY; ``(site, reference_scan)``."""
    site = create_site(client)
    response = upload(client, site["id"], ply_bytes(make_points(3000, seed=1)), reference=True)
    assert response.status_code == 201, response.text
    return site, response.json()["scan"]


def assert_error(response: httpx.Response, status_code: int, error: str | None = None) -> str:
    """Assert the JSON error shape and status; the detail."""
    assert response.status_code == status_code, response.text
    body = response.json()
    assert set(body) == {"error", "detail"}, body
    assert isinstance(body["error"], str) and isinstance(body["detail"], str)
    if error is not None:
        assert body["error"] == error, body
    return body["detail"]


def finish_job(
    api: ApiServer,
    job_id: str,
    n_reference: int,
    n_scan: int,
    *,
    changed: bool = True,
    transform: list[list[float]] | None = None,
) -> dict[str, NDArray]:
    """Play the worker: write the job's result files and rows as a succeeded job; the arrays."""
    from sqlalchemy import update

    from app.clock import utc_now
    from app.db.models import Job, Region

    rng = np.random.default_rng(7)
    arrays = {
        "reference_label": rng.integers(-1, 2, n_reference).astype(np.int8),
        "scan_label": rng.integers(-1, 2, n_scan).astype(np.int8),
    }
    arrays["reference_changed"] = arrays["reference_label"] == 1
    arrays["scan_changed"] = arrays["scan_label"] == 1
    details = {
        "reference_distance": rng.uniform(0, 1, n_reference).astype(np.float32),
        "scan_distance": rng.uniform(0, 1, n_scan).astype(np.float32),
    }
    directory = api.settings.results_dir / job_id
    directory.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(directory / "labels.npz", **arrays)
    np.savez_compressed(directory / "details.npz", **details)
    with transaction(api.settings.sqlalchemy_url) as session:
        session.execute(
            update(Job)
            .where(Job.id == job_id)
            .values(
                status="succeeded",
                progress=1.0,
                attempts=1,
                score=0.5,
                threshold=0.1,
                changed=changed,
                registration={"transform": transform or np.eye(4).tolist(), "rmse": 0.01},
                timings={"align": 0.1},
                n_regions=1,
                labels_path=f"results/{job_id}/labels.npz",
                started_at=utc_now(),
                finished_at=utc_now(),
            )
        )
        session.add(
            Region(
                job_id=job_id,
                ordinal=0,
                kind="added",
                n_points=12,
                centroid=[1.0, 2.0, 0.5],
                bbox_min=[0.5, 1.5, 0.0],
                bbox_max=[1.5, 2.5, 1.0],
                mean_distance=0.4,
                max_distance=0.9,
            )
        )
    return {**arrays, **details}
