"""Dependencies: settings, the request's database session (its one transaction owner), the
authenticated principal with its role checks, and the app's 3D viewers."""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Annotated

from anyio import CancelScope
from fastapi import Depends, Request, Security
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from app.api.concurrency import SAFE_METHODS
from app.api.session_auth import SESSION_COOKIE, principal_from_session_cookie
from app.config import Settings
from app.db.session import read_transaction_wrote, session_factory
from app.services import auth
from app.services.auth import Principal
from app.services.errors import AuthenticationError
from app.services.transaction import commit, end_read_transaction, rollback
from app.viewer.manager import ViewerManager

SESSION_ENDED = (
    "your session has ended: its token was revoked or the session expired; sign in again"
)


async def get_app_settings(request: Request) -> Settings:
    """The settings the app was created with (async: no worker-thread hop for an attribute)."""
    return request.app.state.settings


SettingsDep = Annotated[Settings, Depends(get_app_settings)]


async def get_session(request: Request, settings: SettingsDep) -> AsyncIterator[Session]:
    """A session whose transaction commits when the route returns, before the response is sent.

    Rolled back if the route raises; after-commit work (enqueueing jobs, deleting files of
    deleted rows) runs once the commit succeeded.  Safe methods (GET) get a read-only session
    (a deferred transaction on SQLite: readers never queue for the write lock).  Commits and
    rollbacks run in a worker thread, except ending a read-only transaction that changed
    nothing and has no after-commit work: that is I/O-free, so it runs here and saves a read
    two thread hops (this is async, so creating the session needs none either).
    """
    read_only = request.method in SAFE_METHODS
    session = session_factory(settings.sqlalchemy_url, read_only=read_only)()
    try:
        yield session
    except BaseException:
        await _finish(session, rollback, in_thread=not read_only or _has_callbacks(session))
        raise
    in_thread = (
        not read_only
        or _has_callbacks(session)
        or bool(session.new or session.dirty or session.deleted)
        or read_transaction_wrote(session)
    )
    await _finish(session, commit, in_thread=in_thread)


def _has_callbacks(session: Session) -> bool:
    """Whether after-commit/rollback work is registered (it may do I/O: a worker thread)."""
    return any(session.info.values())


async def _finish(session: Session, end: Callable[[Session], None], *, in_thread: bool) -> None:
    """``end(session)`` (commit or rollback) then close, in a worker thread if ``in_thread``.

    Shielded: a client that disconnects meanwhile does not abandon a commit half way.
    """

    def end_and_close() -> None:
        try:
            end(session)
        finally:
            session.close()

    if not in_thread:
        end_and_close()
        return
    with CancelScope(shield=True):
        await run_in_threadpool(end_and_close)


SessionDep = Annotated[Session, Depends(get_session, scope="function")]

bearer_scheme = HTTPBearer(auto_error=False, description="An API token: `scandiff token create`")


async def get_principal(
    request: Request,
    session: SessionDep,
    settings: SettingsDep,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Security(bearer_scheme)],
) -> Principal:
    """The caller, from ``Authorization: Bearer <token>``; 401 without a valid token.

    A token authenticated in the last few seconds comes from this process's cache, without a
    database read or a worker-thread hop (:class:`app.services.auth.TokenCache` bounds how long
    a revoked token can still be accepted).  A request without an ``Authorization`` header may
    instead carry the dashboard's signed session cookie (:mod:`app.api.session_auth`,
    same-origin checked for writes; never cached: revoking the token ends its sessions at once).
    """
    revocations = auth.revocations_path(settings.data_dir)
    if "authorization" in request.headers:
        token = credentials.credentials if credentials else None
        principal = auth.cached_principal(token, revocations)
        if principal is not None:
            return principal
    return await run_in_threadpool(
        _principal_from_database, request, session, settings, credentials, revocations
    )


def _principal_from_database(
    request: Request,
    session: Session,
    settings: Settings,
    credentials: HTTPAuthorizationCredentials | None,
    revocations: Path,
) -> Principal:
    try:
        if "authorization" not in request.headers:
            principal = principal_from_session_cookie(request, session, settings)
            if principal is not None:
                return principal
        token = credentials.credentials if credentials else None
        return auth.authenticate_and_cache(session, token, revocations)
    finally:
        # Give the connection back now: the route runs in another worker thread, and a
        # connection held across that hop let 50 parallel uploads exhaust the pool (every
        # worker thread waiting for a connection held by a request waiting for a thread).
        end_read_transaction(session)


PrincipalDep = Annotated[Principal, Depends(get_principal)]


async def get_session_principal(
    request: Request,
    session: SessionDep,
    settings: SettingsDep,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Security(bearer_scheme)],
) -> Principal:
    """:func:`get_principal`, except that a request whose session cookie no longer works gets
    a 401 ``session_ended`` (the dashboard then asks to sign in again)."""
    try:
        return await get_principal(request, session, settings, credentials)
    except AuthenticationError:
        if request.cookies.get(SESSION_COOKIE):
            raise AuthenticationError(SESSION_ENDED, code="session_ended") from None
        raise


SessionPrincipalDep = Annotated[Principal, Depends(get_session_principal)]


async def get_writer(principal: PrincipalDep) -> Principal:
    """The caller, if allowed to write (writer or admin); 403 for readers."""
    return auth.require_role(principal, "writer")


WriterDep = Annotated[Principal, Depends(get_writer)]


async def get_viewer_manager(request: Request) -> ViewerManager:
    """The app's per-job 3D viewers (``app.state.viewer_manager``)."""
    return request.app.state.viewer_manager


ViewerManagerDep = Annotated[ViewerManager, Depends(get_viewer_manager)]
