"""What a person's browser uses: the dashboard, sessions, view links and the 3D view.

Routes
------
``GET /``, ``GET /static/{path}``
    The dashboard (``static/``: plain HTML/JS/CSS, nothing from a CDN).
``GET|POST|DELETE /api/v1/session``
    Who is signed in; trade a token for an HttpOnly SameSite=Strict session cookie; sign out.
``POST /api/v1/jobs/{job_id}/view-link``
    ``{"url", "expires_at"}``: a signed link to the job's 3D view that needs no token until it
    expires (``view_link_ttl_seconds``).
``GET /jobs/{job_id}/view`` and its websocket
    viser's client page, and a proxy from its websocket to the job's viser server on 127.0.0.1
    (forwarding the ``viser-v<version>`` subprotocol).  Both need a session cookie of the job's
    organisation or a valid view link; otherwise the page answers 401/403 in words and the
    websocket handshake is refused (HTTP 403).
``GET /api/v1/jobs/{job_id}/view/scene``
    What the job's running 3D view shows: layers with shown/total counts and, per connected
    browser, the region boxes as viser holds them.
"""

from __future__ import annotations

import asyncio
import contextlib
import gzip
import html
import logging
import time
from collections.abc import AsyncIterator
from datetime import UTC, datetime
from functools import lru_cache, partial
from pathlib import Path
from typing import Any

import viser
import websockets.asyncio.client
import websockets.exceptions
from fastapi import APIRouter, FastAPI, Request, WebSocket
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, Response
from pydantic import BaseModel, Field
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool
from starlette.requests import HTTPConnection
from starlette.websockets import WebSocketDisconnect, WebSocketState

from app.api.session_auth import (
    SESSION_COOKIE,
    SESSION_TTL_SECONDS,
    VIEW_COOKIE,
    SignatureInvalidError,
    ViewGrant,
    find_api_token,
    make_session_cookie,
    make_view_link,
    principal_from_session_cookie,
    same_origin,
    secret_key,
    settings_of,
    verify_view_link,
)
from app.db.models import ApiToken, Job, JobStatus, Organisation
from app.db.session import session_factory
from app.services.auth import Principal, authenticate
from app.services.errors import AppError
from app.viewer.loading import ViewUnavailableError, load_job_scene
from app.viewer.manager import DEFAULT_IDLE_SECONDS, ViewerManager
from app.viewer.scene import DEFAULT_POINT_BUDGET

logger = logging.getLogger("scandiff.browser")

STATIC_DIR = Path(__file__).resolve().parents[2] / "static"
VISER_CLIENT_PAGE = Path(viser.__file__).resolve().parent / "client" / "build" / "index.html"
VISER_SUBPROTOCOL_PREFIX = "viser-v"
WEBSOCKET_POLICY_VIOLATION = 1008
WEBSOCKET_INTERNAL_ERROR = 1011
NO_STORE = {"Cache-Control": "no-store"}


async def viewer_lifespan(app: FastAPI) -> AsyncIterator[None]:
    """Stop every per-job viser server when the app shuts down."""
    yield
    manager = getattr(app.state, "viewer_manager", None)
    if manager is not None:
        await run_in_threadpool(manager.stop_all)


router = APIRouter(lifespan=contextlib.asynccontextmanager(viewer_lifespan))


class SessionCreate(BaseModel):
    """The token to trade for a session cookie."""

    token: str = Field(min_length=1, max_length=1000)


# -- helpers -----------------------------------------------------------------------------------


def error_response(status: int, error: str, detail: str) -> JSONResponse:
    """The API's error shape ``{"error", "detail"}``."""
    return JSONResponse({"error": error, "detail": detail}, status_code=status, headers=NO_STORE)


def open_session(connection: HTTPConnection) -> Session:
    """A database session on the app's database (the caller closes it)."""
    return session_factory(settings_of(connection).sqlalchemy_url)()


def request_principal(connection: HTTPConnection, session: Session) -> Principal | None:
    """The caller: a bearer token when sent (must be valid), else the session cookie."""
    authorization = connection.headers.get("authorization", "")
    scheme, _, credentials = authorization.partition(" ")
    if authorization:
        if scheme.lower() != "bearer":
            return None
        try:
            return authenticate(session, credentials.strip())
        except AppError:
            return None
    return principal_from_session_cookie(connection, session)


def job_organisation(session: Session, job_id: str) -> str | None:
    """The organisation owning ``job_id`` (None when no such job)."""
    job = session.get(Job, job_id)
    return job.organisation_id if job is not None else None


def viewer_manager(connection: HTTPConnection) -> ViewerManager:
    """The app's viewer manager, created on first use."""
    state = connection.app.state
    manager = getattr(state, "viewer_manager", None)
    if manager is None:
        settings = settings_of(connection)
        loader = partial(
            load_job_scene,
            settings,
            point_budget=int(getattr(settings, "viewer_point_budget", DEFAULT_POINT_BUDGET)),
        )
        idle_seconds = float(getattr(settings, "viewer_idle_seconds", DEFAULT_IDLE_SECONDS))
        manager = ViewerManager(loader, idle_seconds=idle_seconds)
        state.viewer_manager = manager
    return manager


def message_page(status: int, title: str, message: str, *, sign_in: bool = True) -> HTMLResponse:
    """A small HTML page saying what went wrong, in words."""
    link = '<p><a href="/">Open the dashboard</a> to sign in.</p>' if sign_in else ""
    body = (
        "<!doctype html><html lang='en'><head><meta charset='utf-8'>"
        f"<title>{html.escape(title)} · scandiff</title>"
        "<link rel='stylesheet' href='/static/style.css'></head>"
        f"<body class='message-page'><main><h1>{html.escape(title)}</h1>"
        f"<p>{html.escape(message)}</p>{link}</main></body></html>"
    )
    return HTMLResponse(body, status_code=status, headers=NO_STORE)


@lru_cache(maxsize=1)
def viser_client_page() -> tuple[bytes, bytes]:
    """viser's single-file web client (plain and gzipped), titled for scandiff."""
    page = VISER_CLIENT_PAGE.read_text(encoding="utf-8")
    page = page.replace("<title>Viser</title>", "<title>3D view · scandiff</title>", 1)
    encoded = page.encode("utf-8")
    return encoded, gzip.compress(encoded, compresslevel=6)


def _now_iso(epoch: float) -> str:
    """An epoch time as ISO 8601 UTC."""
    return datetime.fromtimestamp(epoch, UTC).isoformat().replace("+00:00", "Z")


# -- dashboard ---------------------------------------------------------------------------------


@router.get("/", include_in_schema=False)
def dashboard() -> FileResponse:
    """The dashboard's single page."""
    return FileResponse(STATIC_DIR / "index.html", headers={"Cache-Control": "no-cache"})


@router.get("/static/{path:path}", include_in_schema=False)
def static_file(path: str) -> Response:
    """A file of the dashboard (``static/``), never outside it."""
    target = (STATIC_DIR / path).resolve()
    if not target.is_relative_to(STATIC_DIR) or not target.is_file():
        return error_response(404, "not_found", f"no static file {path!r}")
    return FileResponse(target, headers={"Cache-Control": "no-cache"})


# -- sessions ----------------------------------------------------------------------------------


@router.get("/api/v1/session", tags=["session"])
def read_session(request: Request) -> Response:
    """Who the session cookie (or bearer token) belongs to; 401 when signed out."""
    session = open_session(request)
    try:
        principal = request_principal(request, session)
        if principal is None and request.cookies.get(SESSION_COOKIE):
            return error_response(
                401,
                "session_ended",
                "your session has ended: its token was revoked or the session expired; "
                "sign in again",
            )
        if principal is None:
            return error_response(401, "unauthorized", "not signed in")
        organisation = session.get(Organisation, principal.organisation_id)
        return JSONResponse(
            {
                "organisation_id": principal.organisation_id,
                "organisation": organisation.name if organisation else None,
                "role": principal.role,
                "token_id": principal.token_id,
            },
            headers=NO_STORE,
        )
    finally:
        session.close()


@router.post("/api/v1/session", tags=["session"])
def create_session(body: SessionCreate, request: Request) -> Response:
    """Trade an API token for a session cookie (HttpOnly, SameSite=Strict)."""
    if not same_origin(request):
        return error_response(403, "forbidden", "sign in from this server's own dashboard")
    settings = settings_of(request)
    session = open_session(request)
    try:
        token = find_api_token(session, body.token)
        if token is None:
            return error_response(
                401, "unauthorized", "this token is not valid: it is unknown or was revoked"
            )
        organisation = session.get(Organisation, token.organisation_id)
        response = JSONResponse(
            {
                "organisation_id": token.organisation_id,
                "organisation": organisation.name if organisation else None,
                "role": token.role,
                "token_id": token.id,
                "expires_at": _now_iso(time.time() + SESSION_TTL_SECONDS),
            },
            headers=NO_STORE,
        )
        response.set_cookie(
            SESSION_COOKIE,
            make_session_cookie(token, secret_key(settings)),
            max_age=SESSION_TTL_SECONDS,
            path="/",
            httponly=True,
            samesite="strict",
            secure=request.url.scheme == "https",
        )
        return response
    finally:
        session.close()


@router.delete("/api/v1/session", tags=["session"], status_code=204)
def delete_session(request: Request) -> Response:
    """Sign out: clear the session cookie."""
    response = Response(status_code=204, headers=NO_STORE)
    response.delete_cookie(SESSION_COOKIE, path="/", httponly=True, samesite="strict")
    return response


# -- view links and the 3D view ----------------------------------------------------------------


@router.post("/api/v1/jobs/{job_id}/view-link", tags=["jobs"])
def create_view_link(job_id: str, request: Request) -> Response:
    """A signed link to the job's 3D view, valid for ``view_link_ttl_seconds`` without a token."""
    settings = settings_of(request)
    session = open_session(request)
    try:
        principal = request_principal(request, session)
        if principal is None:
            return error_response(401, "unauthorized", "send a valid token or sign in")
        if job_organisation(session, job_id) != principal.organisation_id:
            return error_response(404, "not_found", f"job {job_id} not found")
        token = session.get_one(ApiToken, principal.token_id)
        value, expires_at = make_view_link(
            job_id, token, secret_key(settings), settings.view_link_ttl_seconds
        )
    finally:
        session.close()
    url = str(request.url_for("job_view", job_id=job_id).include_query_params(link=value))
    return JSONResponse({"url": url, "expires_at": _now_iso(expires_at)}, headers=NO_STORE)


def authorise_view(
    connection: HTTPConnection, job_id: str, link: str | None
) -> ViewGrant | tuple[int, str, str]:
    """A grant to see the job's view, or ``(status, title, message)`` saying why not."""
    settings = settings_of(connection)
    key = secret_key(settings)
    session = open_session(connection)
    try:
        owner = job_organisation(session, job_id)
        if link is None:
            link = connection.cookies.get(VIEW_COOKIE) or None
            from_cookie = True
        else:
            from_cookie = False
        principal = principal_from_session_cookie(connection, session)
        if principal is not None and owner is not None and owner == principal.organisation_id:
            return ViewGrant(job_id, principal.token_id, "session", time.time() + 3600)
        if link:
            try:
                return verify_view_link(link, job_id, key, session)
            except SignatureInvalidError as exc:
                if exc.expired:
                    return (
                        403,
                        "This view link has expired",
                        "View links work for a limited time. Ask the sender for a new link, "
                        "or sign in to the dashboard.",
                    )
                if not from_cookie:
                    return (403, "This view link is not valid", f"The link was refused: {exc}.")
        if principal is not None:
            return (404, "Job not found", f"There is no job {job_id} in your organisation.")
        return (
            401,
            "Sign in to see this 3D view",
            "This page needs a session (sign in on the dashboard with your token) or a view link.",
        )
    finally:
        session.close()


@router.get("/jobs/{job_id}/view", name="job_view", include_in_schema=False)
async def job_view(job_id: str, request: Request, link: str | None = None) -> Response:
    """viser's client page for the job, behind the session cookie or a view link."""
    grant = await run_in_threadpool(authorise_view, request, job_id, link)
    if not isinstance(grant, ViewGrant):
        status, title, message = grant
        return message_page(status, title, message)
    problem = await run_in_threadpool(_job_not_viewable, request, job_id)
    if problem is not None:
        return message_page(problem.status, "The 3D view is not available", problem.message)
    # Start loading the scene now, while the browser loads the page.
    manager = viewer_manager(request)
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


def _job_not_viewable(connection: HTTPConnection, job_id: str) -> ViewUnavailableError | None:
    """Why the job's view cannot open (not succeeded, files gone), or None."""
    session = open_session(connection)
    try:
        job = session.get(Job, job_id)
        if job is None:
            return ViewUnavailableError(f"job {job_id} not found", status=404)
        if job.status == JobStatus.FAILED:
            return ViewUnavailableError(
                f"job {job_id} failed: {job.error or 'no reason recorded'}", status=409
            )
        if job.status != JobStatus.SUCCEEDED:
            return ViewUnavailableError(
                f"job {job_id} is still {job.status} ({job.progress:.0%}); the 3D view opens "
                "once it has finished",
                status=409,
            )
        return None
    finally:
        session.close()


def _start_quietly(manager: ViewerManager, job_id: str) -> None:
    """Start the job's viewer in the background; failures show up when the websocket asks."""
    try:
        manager.get(job_id)
    except Exception:
        logger.exception("could not start the 3D view of job %s", job_id)


@router.websocket("/jobs/{job_id}/view")
async def job_view_socket(websocket: WebSocket, job_id: str) -> None:
    """Proxy the viser client's websocket to the job's viser server."""
    if not same_origin(websocket):
        await websocket.close(code=WEBSOCKET_POLICY_VIOLATION)
        return
    grant = await run_in_threadpool(authorise_view, websocket, job_id, None)
    if not isinstance(grant, ViewGrant):
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
    manager = viewer_manager(websocket)
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


@router.get("/api/v1/jobs/{job_id}/view/scene", tags=["jobs"])
def job_view_scene(job_id: str, request: Request) -> Response:
    """What the job's running 3D view shows (layers, counts, region boxes per browser)."""
    session = open_session(request)
    try:
        principal = request_principal(request, session)
        if principal is None:
            return error_response(401, "unauthorized", "send a valid token or sign in")
        if job_organisation(session, job_id) != principal.organisation_id:
            return error_response(404, "not_found", f"job {job_id} not found")
    finally:
        session.close()
    viewer = viewer_manager(request).find(job_id)
    if viewer is None:
        return JSONResponse({"job_id": job_id, "running": False}, headers=NO_STORE)
    return JSONResponse({"running": True, **viewer.to_json_dict()}, headers=NO_STORE)
