"""What a person's browser uses besides the API proper: the dashboard, sessions and view links.

Routes
------
``GET /``, ``GET /static/{path}``
    The dashboard (``static/``, shipped in the wheel as ``app/static``: plain HTML/JS/CSS,
    nothing from a CDN).
``GET|POST|DELETE /api/v1/session``
    Who is signed in; trade a token for an HttpOnly SameSite=Strict session cookie; sign out.
``POST /api/v1/jobs/{job_id}/view-link``
    ``{"url", "expires_at"}``: a signed link to the job's 3D view that needs no token until it
    expires (``view_link_ttl_seconds``).
``GET /api/v1/jobs/{job_id}/view/scene``
    What the job's running 3D view in this API process shows: layers with shown/total counts
    and, per connected browser, the region boxes as viser holds them.
``GET /jobs/{job_id}/view`` and its websocket
    The 3D view itself (:mod:`app.viewer.routes`), built here with :func:`authorise_view`.

The routes use the API's dependencies (:mod:`app.api.deps`: settings, the request's database
session, the caller from a bearer token or the session cookie) and its errors
(:mod:`app.services.errors`, rendered by :mod:`app.api.errors`).
"""

from __future__ import annotations

import time
from datetime import UTC, datetime
from functools import partial
from os import PathLike, stat_result
from pathlib import Path

from fastapi import APIRouter, FastAPI, Request
from fastapi.responses import FileResponse, JSONResponse, Response
from pydantic import BaseModel, Field
from sqlalchemy.orm import Session
from starlette.requests import HTTPConnection
from starlette.staticfiles import StaticFiles
from starlette.types import Scope

from app.api.deps import (
    PrincipalDep,
    SessionDep,
    SessionPrincipalDep,
    SettingsDep,
    ViewerManagerDep,
)
from app.api.session_auth import (
    SESSION_COOKIE,
    SESSION_TTL_SECONDS,
    SignatureInvalidError,
    make_session_cookie,
    make_view_link,
    principal_from_session_cookie,
    same_origin,
    secret_key,
    verify_view_link,
)
from app.clock import iso_utc
from app.config import Settings
from app.db.models import ApiToken, Job, Organisation
from app.db.session import session_factory
from app.services import auth, jobs
from app.services.auth import Principal
from app.services.errors import AuthenticationError, PermissionDeniedError
from app.viewer.access import VIEW_COOKIE, ViewGrant, ViewRefusal
from app.viewer.routes import build_viewer_router, new_viewer_manager

STATIC_DIR = (Path(__file__).resolve().parents[1] / "static").resolve()
"""The dashboard's files: ``app/static`` (in a checkout a symlink to the top-level ``static/``; in
an installed wheel the files themselves, shipped as package data)."""
NO_STORE = {"Cache-Control": "no-store"}
SESSION_GRANT_SECONDS = 3600
"""How long a view grant from a session cookie is good for (the cookie is re-read each time)."""


class DashboardFiles(StaticFiles):
    """The dashboard's files, revalidated on every use (``Cache-Control: no-cache``)."""

    def file_response(
        self,
        full_path: str | PathLike[str],
        stat_result: stat_result,
        scope: Scope,
        status_code: int = 200,
    ) -> Response:
        """The file's response with ``Cache-Control: no-cache``."""
        response = super().file_response(full_path, stat_result, scope, status_code)
        response.headers["Cache-Control"] = "no-cache"
        return response


class SessionCreate(BaseModel):
    """The token to trade for a session cookie."""

    token: str = Field(min_length=1, max_length=1000)


router = APIRouter()


def include_browser_routes(app: FastAPI, settings: Settings) -> None:
    """Add the dashboard, the session routes and the 3D view (and its viewers) to ``app``."""
    manager = new_viewer_manager(settings)
    app.state.viewer_manager = manager
    app.include_router(router)
    app.include_router(build_viewer_router(manager, settings, partial(authorise_view, settings)))
    app.mount("/static", DashboardFiles(directory=STATIC_DIR), name="static")


def epoch_iso(epoch: float) -> str:
    """An epoch time as ISO 8601 UTC."""
    return iso_utc(datetime.fromtimestamp(epoch, UTC))


def signed_in_answer(session: Session, principal: Principal, **extra: str) -> JSONResponse:
    """Who is signed in: the principal and its organisation's name (never cached)."""
    organisation = session.get(Organisation, principal.organisation_id)
    return JSONResponse(
        {
            "organisation_id": principal.organisation_id,
            "organisation": organisation.name if organisation else None,
            "role": principal.role,
            "token_id": principal.token_id,
            **extra,
        },
        headers=NO_STORE,
    )


# -- dashboard ---------------------------------------------------------------------------------


@router.get("/", include_in_schema=False)
def dashboard() -> FileResponse:
    """The dashboard's single page."""
    return FileResponse(STATIC_DIR / "index.html", headers={"Cache-Control": "no-cache"})


# -- sessions ----------------------------------------------------------------------------------


@router.get("/api/v1/session", tags=["session"])
def read_session(principal: SessionPrincipalDep, session: SessionDep) -> Response:
    """Who the session cookie (or bearer token) belongs to; 401 when signed out."""
    return signed_in_answer(session, principal)


@router.post("/api/v1/session", tags=["session"])
def create_session(
    body: SessionCreate, request: Request, session: SessionDep, settings: SettingsDep
) -> Response:
    """Trade an API token for a session cookie (HttpOnly, SameSite=Strict)."""
    if not same_origin(request):
        raise PermissionDeniedError("sign in from this server's own dashboard")
    try:
        principal = auth.authenticate(session, body.token.strip())
    except AuthenticationError:
        raise AuthenticationError("this token is not valid: it is unknown or was revoked") from None
    response = signed_in_answer(
        session, principal, expires_at=epoch_iso(time.time() + SESSION_TTL_SECONDS)
    )
    response.set_cookie(
        SESSION_COOKIE,
        make_session_cookie(principal.token_id, secret_key(settings)),
        max_age=SESSION_TTL_SECONDS,
        path="/",
        httponly=True,
        samesite="strict",
        secure=request.url.scheme == "https",
    )
    return response


@router.delete("/api/v1/session", tags=["session"], status_code=204)
def delete_session() -> Response:
    """Sign out: clear the session cookie."""
    response = Response(status_code=204, headers=NO_STORE)
    response.delete_cookie(SESSION_COOKIE, path="/", httponly=True, samesite="strict")
    return response


# -- view links and the 3D view ----------------------------------------------------------------


@router.post("/api/v1/jobs/{job_id}/view-link", tags=["jobs"])
def create_view_link(
    job_id: str,
    request: Request,
    principal: PrincipalDep,
    session: SessionDep,
    settings: SettingsDep,
) -> Response:
    """A signed link to the job's 3D view, valid for ``view_link_ttl_seconds`` without a token."""
    jobs.get_job(session, principal, job_id)
    token = session.get_one(ApiToken, principal.token_id)
    value, expires_at = make_view_link(
        job_id, token, secret_key(settings), settings.view_link_ttl_seconds
    )
    url = str(request.url_for("job_view", job_id=job_id).include_query_params(link=value))
    return JSONResponse({"url": url, "expires_at": epoch_iso(expires_at)}, headers=NO_STORE)


@router.get("/api/v1/jobs/{job_id}/view/scene", tags=["jobs"])
def job_view_scene(
    job_id: str, principal: PrincipalDep, session: SessionDep, manager: ViewerManagerDep
) -> Response:
    """What the job's running 3D view shows (layers, counts, region boxes per browser)."""
    jobs.get_job(session, principal, job_id)
    viewer = manager.find(job_id)
    if viewer is None:
        return JSONResponse({"job_id": job_id, "running": False}, headers=NO_STORE)
    return JSONResponse({"running": True, **viewer.to_json_dict()}, headers=NO_STORE)


def authorise_view(
    settings: Settings, connection: HTTPConnection, job_id: str, link: str | None
) -> ViewGrant | ViewRefusal:
    """A grant to see the job's view (session cookie of its organisation, or view link), or why not.

    ``link`` None reads the view-link cookie instead (the websocket's case); a websocket must
    come from this server's own pages (``Origin``).
    """
    if connection.scope["type"] == "websocket" and not same_origin(connection):
        return ViewRefusal(403, "Not allowed", "The 3D view opens from this server's pages only.")
    from_cookie = link is None
    if link is None:
        link = connection.cookies.get(VIEW_COOKIE) or None
    with session_factory(settings.sqlalchemy_url, read_only=True)() as session:
        job = session.get(Job, job_id)
        owner = job.organisation_id if job is not None else None
        principal = principal_from_session_cookie(connection, session, settings)
        if principal is not None and owner is not None and owner == principal.organisation_id:
            return ViewGrant(
                job_id, principal.token_id, "session", time.time() + SESSION_GRANT_SECONDS
            )
        if link:
            try:
                return verify_view_link(link, job_id, secret_key(settings), session)
            except SignatureInvalidError as exc:
                if exc.expired:
                    return ViewRefusal(
                        403,
                        "This view link has expired",
                        "View links work for a limited time. Ask the sender for a new link, "
                        "or sign in to the dashboard.",
                    )
                if not from_cookie:
                    return ViewRefusal(
                        403, "This view link is not valid", f"The link was refused: {exc}."
                    )
    if principal is not None:
        return ViewRefusal(404, "Job not found", f"There is no job {job_id} in your organisation.")
    return ViewRefusal(
        401,
        "Sign in to see this 3D view",
        "This page needs a session (sign in on the dashboard with your token) or a view link.",
    )
