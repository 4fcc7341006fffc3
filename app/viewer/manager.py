"""Per-job viser servers, started on demand on 127.0.0.1 and stopped when idle.

The browser never talks to a viser server directly: FastAPI serves the client page and proxies
its websocket (:mod:`app.viewer.routes`), so every connection passes the service's auth.  Each job
gets its own ``ViserServer(host="127.0.0.1", port=0)``; the port actually bound is read back
with ``get_port()`` (viser silently moves to port+1 when a port is busy).  Each server also gets
a random per-view secret that only this process knows: the server closes any websocket whose
handshake does not present it (:mod:`app.viewer.viser_guard`), so the loopback port serves
nothing to other processes or users on the host.  A reaper thread stops servers that had no
proxied connection for ``idle_seconds``.

Every API process keeps its own viewers.  The scene is built deterministically from the job's
stored files and rows (:func:`app.viewer.loading.load_job_scene`), so whichever process receives
a view's websocket starts (or reuses) its own server for that job: no sticky sessions needed.
"""

from __future__ import annotations

import logging
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import numpy as np
import viser
from numpy.typing import NDArray

from app.config import DEFAULT_VIEWER_IDLE_SECONDS
from app.viewer.scene import SceneData
from app.viewer.viser_guard import require_view_secret
from app.viewer.viser_scene import ClientScene, build_client_scene, configure_server

logger = logging.getLogger("scandiff.viewer")

SceneLoader = Callable[[str], tuple[SceneData, str]]
"""Loads a job's scene: ``loader(job_id) -> (scene data, title)``."""
Corner = NDArray[np.float64]
JobBoxLoader = Callable[[str, Corner, Corner, Corner], SceneData]
"""``(job_id, low, high, origin) -> scene``: a box of the job at full density."""

DEFAULT_IDLE_SECONDS = DEFAULT_VIEWER_IDLE_SECONDS
"""Seconds a viewer outlives its last connection; the default of ``viewer_idle_seconds``."""


@dataclass
class JobViewer:
    """One running viser server showing one job."""

    job_id: str
    server: viser.ViserServer
    data: SceneData
    title: str
    secret: str
    """What the proxy presents to this server (``VIEW_SECRET_HEADER``); never leaves the process."""
    started_at: float
    last_active: float
    connections: int = 0
    clients: dict[int, ClientScene] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)

    @property
    def port(self) -> int:
        """The port viser actually bound on 127.0.0.1."""
        return int(self.server.get_port())

    def to_json_dict(self) -> dict[str, Any]:
        """The builder's record plus what viser holds for each connected browser."""
        with self.lock:
            clients = [scene.to_json_dict(self.data.origin) for scene in self.clients.values()]
        return {
            "job_id": self.job_id,
            "connections": self.connections,
            "scene": self.data.to_json_dict(),
            "clients": clients,
        }


class ViewerManager:
    """Starts, finds and stops the per-job viser servers of one API process."""

    def __init__(
        self,
        loader: SceneLoader,
        *,
        idle_seconds: float = DEFAULT_IDLE_SECONDS,
        reap_interval: float | None = None,
        box_loader: JobBoxLoader | None = None,
    ) -> None:
        self.loader = loader
        self.box_loader = box_loader
        self.idle_seconds = idle_seconds
        self.reap_interval = reap_interval or max(min(idle_seconds / 4.0, 30.0), 0.5)
        self._viewers: dict[str, JobViewer] = {}
        self._starting: dict[str, threading.Lock] = {}
        self._lock = threading.Lock()
        self._stop_event = threading.Event()
        self._reaper: threading.Thread | None = None

    def get(self, job_id: str) -> JobViewer:
        """The job's viewer, started (scene loaded, server bound) if it is not running."""
        with self._lock:
            viewer = self._viewers.get(job_id)
            if viewer is not None:
                viewer.last_active = time.monotonic()
                return viewer
            start_lock = self._starting.setdefault(job_id, threading.Lock())
        with start_lock:  # one start per job even when page and websocket race
            with self._lock:
                viewer = self._viewers.get(job_id)
            if viewer is None:
                viewer = self._start(job_id)
                with self._lock:
                    self._viewers[job_id] = viewer
                    self._starting.pop(job_id, None)
            self._ensure_reaper()
            return viewer

    def find(self, job_id: str) -> JobViewer | None:
        """The job's viewer if it is running."""
        with self._lock:
            return self._viewers.get(job_id)

    def running(self) -> list[str]:
        """Job ids with a running viewer."""
        with self._lock:
            return sorted(self._viewers)

    def connection_opened(self, job_id: str) -> None:
        """A proxied websocket to the job's viewer opened."""
        viewer = self.find(job_id)
        if viewer is not None:
            with viewer.lock:
                viewer.connections += 1
                viewer.last_active = time.monotonic()

    def connection_closed(self, job_id: str) -> None:
        """A proxied websocket to the job's viewer closed."""
        viewer = self.find(job_id)
        if viewer is not None:
            with viewer.lock:
                viewer.connections = max(viewer.connections - 1, 0)
                viewer.last_active = time.monotonic()

    def reap_idle(self, now: float | None = None) -> list[str]:
        """Stop viewers without connections for ``idle_seconds``; the job ids stopped."""
        now = time.monotonic() if now is None else now
        with self._lock:
            idle = [
                job_id
                for job_id, viewer in self._viewers.items()
                if viewer.connections == 0 and now - viewer.last_active >= self.idle_seconds
            ]
        for job_id in idle:
            self.stop(job_id)
        return idle

    def stop(self, job_id: str) -> bool:
        """Stop the job's viewer; whether one was running."""
        with self._lock:
            viewer = self._viewers.pop(job_id, None)
        if viewer is None:
            return False
        logger.info("viewer stopped", extra={"job_id": job_id, "port": viewer.port})
        viewer.server.stop()
        return True

    def stop_all(self) -> None:
        """Stop every viewer and the reaper."""
        self._stop_event.set()
        for job_id in self.running():
            self.stop(job_id)
        if self._reaper is not None and self._reaper is not threading.current_thread():
            self._reaper.join(timeout=5.0)

    def _start(self, job_id: str) -> JobViewer:
        """Load the job's scene and start a viser server for it."""
        data, title = self.loader(job_id)
        server = viser.ViserServer(host="127.0.0.1", port=0, label=title, verbose=False)
        secret = secrets.token_urlsafe(32)
        try:
            check = require_view_secret(server, secret)  # before the scene or its callbacks exist
        except BaseException:
            server.stop()
            raise
        now = time.monotonic()
        viewer = JobViewer(
            job_id, server, data, title, secret=secret, started_at=now, last_active=now
        )
        configure_server(server, data, title)

        @server.on_client_connect
        def _(client: viser.ClientHandle) -> None:
            if check.refused(client.client_id):
                return  # closed for lacking the secret: build nothing for it
            box_loader = None if self.box_loader is None else partial(self.box_loader, job_id)
            scene = build_client_scene(client, data, title, box_loader)
            with viewer.lock:
                viewer.clients[client.client_id] = scene

        @server.on_client_disconnect
        def _(client: viser.ClientHandle) -> None:
            with viewer.lock:
                viewer.clients.pop(client.client_id, None)

        logger.info(
            "viewer started",
            extra={"job_id": job_id, "port": viewer.port, "points": data.n_shown},
        )
        return viewer

    def _ensure_reaper(self) -> None:
        """Start the idle reaper thread once."""
        with self._lock:
            if self._reaper is not None and self._reaper.is_alive():
                return
            self._stop_event.clear()
            self._reaper = threading.Thread(
                target=self._reap_forever, name="scandiff-viewer-reaper", daemon=True
            )
            self._reaper.start()

    def _reap_forever(self) -> None:
        """Reap idle viewers every ``reap_interval`` until :meth:`stop_all`."""
        while not self._stop_event.wait(self.reap_interval):
            try:
                self.reap_idle()
            except Exception:  # a reaper that dies would leak servers
                logger.exception("viewer reaper failed")
