"""Dependencies: settings, the request's database session (its one transaction owner), and the
authenticated principal with its role checks."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, Request, Security
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session

from app.api.concurrency import SAFE_METHODS
from app.api.session_auth import principal_from_session_cookie
from app.config import Settings
from app.db.session import session_factory
from app.services import auth
from app.services.auth import Principal
from app.services.transaction import commit, end_read_transaction, rollback


def get_app_settings(request: Request) -> Settings:
    """The settings the app was created with."""
    return request.app.state.settings


SettingsDep = Annotated[Settings, Depends(get_app_settings)]


def get_session(request: Request, settings: SettingsDep) -> Iterator[Session]:
    """A session whose transaction commits when the route returns, before the response is sent.

    Rolled back if the route raises; after-commit work (enqueueing jobs, deleting files of
    deleted rows) runs once the commit succeeded.  Safe methods (GET) get a read-only session
    (a deferred transaction on SQLite: readers never queue for the write lock).
    """
    read_only = request.method in SAFE_METHODS
    session = session_factory(settings.sqlalchemy_url, read_only=read_only)()
    try:
        yield session
        commit(session)
    except BaseException:
        rollback(session)
        raise
    finally:
        session.close()


SessionDep = Annotated[Session, Depends(get_session, scope="function")]

bearer_scheme = HTTPBearer(auto_error=False, description="An API token: `scandiff token create`")


def get_principal(
    request: Request,
    session: SessionDep,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Security(bearer_scheme)],
) -> Principal:
    """The caller, from ``Authorization: Bearer <token>``; 401 without a valid token.

    A request without an ``Authorization`` header may instead carry the dashboard's signed
    session cookie (:mod:`app.api.session_auth`, same-origin checked for writes).
    """
    try:
        if "authorization" not in request.headers:
            principal = principal_from_session_cookie(request, session)
            if principal is not None:
                return principal
        return auth.authenticate(session, credentials.credentials if credentials else None)
    finally:
        # Give the connection back now: the route runs in another worker thread, and a
        # connection held across that hop let 50 parallel uploads exhaust the pool (every
        # worker thread waiting for a connection held by a request waiting for a thread).
        end_read_transaction(session)


PrincipalDep = Annotated[Principal, Depends(get_principal)]


def get_writer(principal: PrincipalDep) -> Principal:
    """The caller, if allowed to write (writer or admin); 403 for readers."""
    return auth.require_role(principal, "writer")


WriterDep = Annotated[Principal, Depends(get_writer)]
