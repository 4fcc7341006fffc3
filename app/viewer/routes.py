"""The 3D view of a job in the browser: viser's client page and a proxy to its websocket.

Routes
------
``GET /jobs/{job_id}/view`` and its websocket
    viser's client page, and a proxy from its websocket to the job's viser server on 127.0.0.1
    (forwarding the ``viser-v<version>`` subprotocol and presenting the view's secret, without
    which the viser server closes the connection).  Both need what the router's
    :data:`~app.viewer.access.ViewAuthoriser` grants (the API's: a session cookie of the job's
    organisation or a valid view link); otherwise the page answers 401/403 in words and the
    websocket handshake is refused (HTTP 403).

The API builds this router for each app (:func:`build_viewer_router`), passing its authoriser:
the viewer imports nothing of the API.
"""

from __future__ import annotations

import asyncio
import contextlib
import gzip
import html
import logging
import time
from collections.abc import AsyncIterator
from functools import lru_cache, partial
from pathlib import Path
from typing import Any

import viser
import websockets.asyncio.client
import websockets.exceptions
from fastapi import APIRouter, FastAPI, Request, WebSocket
from fastapi.responses import HTMLResponse, Response
from starlette.concurrency import run_in_threadpool
from starlette.websockets import WebSocketDisconnect, WebSocketState

from app.config import Settings
from app.viewer.access import VIEW_COOKIE, ViewAuthoriser, ViewRefusal
from app.viewer.loading import (
    ViewUnavailableError,
    job_view_problem,
    load_job_box,
    load_job_scene,
)
from app.viewer.manager import ViewerManager
from app.viewer.viser_guard import VIEW_SECRET_HEADER

logger = logging.getLogger("scandiff.browser")

VISER_CLIENT_PAGE = Path(viser.__file__).resolve().parent / "client" / "build" / "index.html"
VISER_SUBPROTOCOL_PREFIX = "viser-v"
WEBSOCKET_POLICY_VIOLATION = 1008
WEBSOCKET_INTERNAL_ERROR = 1011
NO_STORE = {"Cache-Control": "no-store"}


def new_viewer_manager(settings: Settings) -> ViewerManager:
    """The per-job viser servers of one app, loading scenes as ``settings`` say."""
    loader = partial(load_job_scene, settings, point_budget=settings.viewer_point_budget)
    return ViewerManager(
        loader,
        idle_seconds=settings.viewer_idle_seconds,
        box_loader=partial(_job_box, settings),
    )


def _job_box(settings: Settings, job_id: str, low: Any, high: Any, origin: Any) -> Any:
    """A box of the job at full density, up to the point budget (the box panel's loader)."""
    return load_job_box(
        settings, job_id, low, high, point_budget=settings.viewer_point_budget, origin=origin
    )


def build_viewer_router(
    manager: ViewerManager, settings: Settings, authorise: ViewAuthoriser
) -> APIRouter:
    """The view page and its websocket proxy, behind ``authorise``; stops ``manager`` at exit."""

    @contextlib.asynccontextmanager
    async def stop_viewers_at_exit(app: FastAPI) -> AsyncIterator[None]:
        yield
        await run_in_threadpool(manager.stop_all)

    router = APIRouter(lifespan=stop_viewers_at_exit)

    @router.get("/jobs/{job_id}/view", name="job_view", include_in_schema=False)
    async def job_view(job_id: str, request: Request, link: str | None = None) -> Response:
        """viser's client page for the job, behind the session cookie or a view link."""
        return await view_page(request, job_id, link, manager, settings, authorise)

    @router.websocket("/jobs/{job_id}/view")
    async def job_view_socket(websocket: WebSocket, job_id: str) -> None:
        """Proxy the viser client's websocket to the job's viser server."""
        await proxy_view_socket(websocket, job_id, manager, authorise)

    return router


def message_page(status: int, title: str, message: str) -> HTMLResponse:
    """A small HTML page saying what went wrong, in words, with a way to sign in."""
    body = (
        "<!doctype html><html lang='en'><head><meta charset='utf-8'>"
        f"<title>{html.escape(title)} · scandiff</title>"
        "<link rel='stylesheet' href='/static/style.css'></head>"
        f"<body class='message-page'><main><h1>{html.escape(title)}</h1>"
        f"<p>{html.escape(message)}</p>"
        '<p><a href="/">Open the dashboard</a> to sign in.</p></main></body></html>'
    )
    return HTMLResponse(body, status_code=status, headers=NO_STORE)


REVIEW_SCRIPT = "/static/view-review.js"
"""The dashboard's review panel, loaded by the 3D view page (static/view-review.js)."""


@lru_cache(maxsize=1)
def viser_client_page() -> tuple[bytes, bytes]:
    """viser's single-file web client (plain and gzipped), titled for scandiff, with the
    review panel's script."""
    page = VISER_CLIENT_PAGE.read_text(encoding="utf-8")
    page = page.replace("<title>Viser</title>", "<title>3D view · scandiff</title>", 1)
    # The review panel (verdict buttons) over the scene: the dashboard's own module.
    review = f'<script type="module" src="{REVIEW_SCRIPT}"></script>'
    page = page.replace("</body>", review + "</body>", 1)
    encoded = page.encode("utf-8")
    return encoded, gzip.compress(encoded, compresslevel=6)


async def view_page(
    request: Request,
    job_id: str,
    link: str | None,
    manager: ViewerManager,
    settings: Settings,
    authorise: ViewAuthoriser,
) -> Response:
    """The client page once ``authorise`` grants it and the job can be shown, else words."""
    grant = await run_in_threadpool(authorise, request, job_id, link)
    if isinstance(grant, ViewRefusal):
        return message_page(grant.status, grant.title, grant.message)
    problem = await run_in_threadpool(job_view_problem, settings, job_id)
    if problem is not None:
        return message_page(problem.status, "The 3D view is not available", problem.message)
    # Start loading the scene now, while the browser loads the page.
    asyncio.get_running_loop().run_in_executor(None, _start_quietly, manager, job_id)
    plain, compressed = viser_client_page()
    use_gzip = "gzip" in request.headers.get("accept-encoding", "")
    response = Response(
        compressed if use_gzip else plain,
        media_type="text/html; charset=utf-8",
        headers={**NO_STORE, **({"Content-Encoding": "gzip"} if use_gzip else {})},
    )
    if link and grant.via == "link":
        # The viser client drops the query string when it opens its websocket: remember the
        # link in a cookie scoped to this view's path, for as long as the link is valid.
        response.set_cookie(
            VIEW_COOKIE,
            link,
            max_age=max(int(grant.expires_at - time.time()), 1),
            path=request.url.path,
            httponly=True,
            samesite="strict",
            secure=request.url.scheme == "https",
        )
    return response


def _start_quietly(manager: ViewerManager, job_id: str) -> None:
    """Start the job's viewer in the background; failures show up when the websocket asks."""
    try:
        manager.get(job_id)
    except Exception:
        logger.exception("could not start the 3D view of job %s", job_id)


async def proxy_view_socket(
    websocket: WebSocket, job_id: str, manager: ViewerManager, authorise: ViewAuthoriser
) -> None:
    """Proxy the browser's websocket to the job's viser server once ``authorise`` grants it."""
    grant = await run_in_threadpool(authorise, websocket, job_id, None)
    if isinstance(grant, ViewRefusal):
        await websocket.close(code=WEBSOCKET_POLICY_VIOLATION)  # before accept: HTTP 403
        return
    requested = [
        protocol
        for protocol in websocket.scope.get("subprotocols", [])
        if protocol.startswith(VISER_SUBPROTOCOL_PREFIX)
    ]
    # Accept at once with the client's viser subprotocol: loading a large scene can take longer
    # than the 5 s the viser client waits for a handshake before it retries.
    await websocket.accept(subprotocol=requested[0] if requested else None)
    try:
        viewer = await run_in_threadpool(manager.get, job_id)
    except ViewUnavailableError as exc:
        logger.info("3D view of job %s unavailable: %s", job_id, exc.message)
        reason = exc.message.encode()[:120].decode(errors="ignore")  # a close reason <= 123 B
        await websocket.close(code=WEBSOCKET_POLICY_VIOLATION, reason=reason)
        return
    except Exception:
        logger.exception("could not start the 3D view of job %s", job_id)
        await websocket.close(code=WEBSOCKET_INTERNAL_ERROR, reason="the 3D view failed to load")
        return
    try:
        upstream = await websockets.asyncio.client.connect(
            f"ws://127.0.0.1:{viewer.port}",
            subprotocols=requested or None,  # type: ignore[arg-type]
            additional_headers={VIEW_SECRET_HEADER: viewer.secret},
            max_size=None,
            compression=None,
            open_timeout=15,
        )
    except (OSError, websockets.exceptions.WebSocketException, TimeoutError):
        logger.exception("viser server of job %s did not accept the proxy", job_id)
        await websocket.close(code=WEBSOCKET_INTERNAL_ERROR, reason="the 3D view is unreachable")
        return
    manager.connection_opened(job_id)
    try:
        await _pump(websocket, upstream)
    finally:
        manager.connection_closed(job_id)
        await upstream.close()
        if websocket.client_state != WebSocketState.DISCONNECTED:
            code = upstream.close_code
            forwardable = code is not None and code not in (1005, 1006, 1015)
            with contextlib.suppress(RuntimeError, WebSocketDisconnect):
                await websocket.close(
                    code=code if forwardable else 1000,
                    reason=(upstream.close_reason or "") if forwardable else "",
                )


async def _pump(browser: WebSocket, upstream: Any) -> None:
    """Copy messages both ways until either side closes."""

    async def browser_to_viser() -> None:
        while True:
            message = await browser.receive()
            if message["type"] == "websocket.disconnect":
                return
            if message.get("bytes") is not None:
                await upstream.send(message["bytes"])
            elif message.get("text") is not None:
                await upstream.send(message["text"])

    async def viser_to_browser() -> None:
        async for message in upstream:
            if isinstance(message, bytes):
                await browser.send_bytes(message)
            else:
                await browser.send_text(message)

    tasks = [
        asyncio.create_task(browser_to_viser()),
        asyncio.create_task(viser_to_browser()),
    ]
    done, pending = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    for task in pending:
        task.cancel()
    for task in pending:
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await task
    for task in done:
        exception = task.exception()
        if exception is not None and not isinstance(
            exception, (WebSocketDisconnect, websockets.exceptions.ConnectionClosed)
        ):
            logger.warning("3D view proxy stopped: %r", exception)
