"""Browser sessions and view links: signed cookies and URLs, no server-side session table.

* A **session cookie** (``scandiff_session``, HttpOnly, SameSite=Strict) is what the dashboard
  gets for a valid API token (``POST /api/v1/session``).  It holds the token's *id* (never the
  token) and an expiry, signed with HMAC-SHA256; every request re-reads the token row, so
  revoking the token ends its sessions at once.
* A **view link** (``/jobs/{job_id}/view?link=...``) lets someone without a token open one job's
  3D view until it expires (``view_link_ttl_seconds``, 24 h by default).  It is signed for that
  job and names the token that made it (revoking the token kills its links).  Opening the link
  also sets a cookie scoped to that view's path, because the viser client drops the query
  string when it opens its websocket.

The signing key is ``Settings.secret_key`` or, when unset, a random key generated once into
``<data_dir>/secret-key`` (mode 0600) and shared by every process using that directory.

The API's bearer-token dependency accepts the session cookie too by calling
:func:`principal_from_session_cookie` when a request has no ``Authorization`` header.
"""

from __future__ import annotations

import time
from urllib.parse import urlsplit

from sqlalchemy.orm import Session
from starlette.requests import HTTPConnection

from app.config import Settings
from app.db.models import ApiToken
from app.kit.signing import (
    VIEW_LINK_PURPOSE,
    SignatureInvalidError,
    sign,
    signing_key,
    verify,
    view_link_value,
)
from app.services.auth import Principal
from app.viewer.access import ViewGrant

SESSION_COOKIE = "scandiff_session"
SESSION_TTL_SECONDS = 12 * 3600
SESSION_PURPOSE = "session"
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})


# -- keys and signatures -----------------------------------------------------------------------


def secret_key(settings: Settings) -> bytes:
    """The signing key: ``settings.secret_key`` or the one generated in the data directory."""
    return signing_key(settings.secret_key, settings.data_dir)


# -- tokens and sessions -----------------------------------------------------------------------


def live_token_by_id(session: Session, token_id: str) -> ApiToken | None:
    """The token row with this id unless it was revoked."""
    row = session.get(ApiToken, token_id)
    return row if row is not None and row.revoked_at is None else None


def make_session_cookie(token_id: str, key: bytes, ttl: float = SESSION_TTL_SECONDS) -> str:
    """The signed session cookie value for the token ``token_id``."""
    return sign({"tid": token_id, "exp": int(time.time() + ttl)}, SESSION_PURPOSE, key)


def session_token_id(connection: HTTPConnection, key: bytes) -> str | None:
    """The token id in the connection's session cookie if signed with ``key``, else None."""
    value = connection.cookies.get(SESSION_COOKIE)
    if not value:
        return None
    try:
        payload = verify(value, SESSION_PURPOSE, key)
    except SignatureInvalidError:
        return None
    token_id = payload.get("tid")
    return token_id if isinstance(token_id, str) else None


def same_origin(connection: HTTPConnection) -> bool:
    """Whether the ``Origin`` header (when sent) names this server's host."""
    origin = connection.headers.get("origin")
    if not origin:
        return True
    host = connection.headers.get("host", "")
    return urlsplit(origin).netloc.lower() == host.lower()


def token_from_session_cookie(
    connection: HTTPConnection, session: Session, settings: Settings
) -> ApiToken | None:
    """The live token row behind the request's session cookie, or None.

    For requests that change things (not GET/HEAD/OPTIONS) and for websockets the ``Origin``,
    when present, must be this server: a second guard against cross-site requests besides
    SameSite=Strict.
    """
    token_id = session_token_id(connection, secret_key(settings))
    if token_id is None:
        return None
    method = connection.scope.get("method", "GET") if connection.scope["type"] == "http" else ""
    if method not in SAFE_METHODS and not same_origin(connection):
        return None
    return live_token_by_id(session, token_id)


def principal_from_session_cookie(
    connection: HTTPConnection, session: Session, settings: Settings
) -> Principal | None:
    """The principal of the request's session cookie (for the API's bearer dependency)."""
    token = token_from_session_cookie(connection, session, settings)
    if token is None:
        return None
    return Principal(organisation_id=token.organisation_id, role=token.role, token_id=token.id)


# -- view links --------------------------------------------------------------------------------


def make_view_link(job_id: str, token: ApiToken, key: bytes, ttl: float) -> tuple[str, float]:
    """A signed view-link value for ``job_id`` and when it expires (epoch seconds)."""
    return view_link_value(job_id, token.id, key, ttl)


def verify_view_link(value: str, job_id: str, key: bytes, session: Session) -> ViewGrant:
    """The grant a view-link value gives for ``job_id``.

    Raises
    ------
    SignatureInvalidError
        Tampered, for another job, expired (``expired=True``) or its token was revoked.
    """
    payload = verify(value, VIEW_LINK_PURPOSE, key)
    if payload.get("job") != job_id:
        raise SignatureInvalidError("this link is for another job")
    token_id = payload.get("tid")
    if not isinstance(token_id, str) or live_token_by_id(session, token_id) is None:
        raise SignatureInvalidError("the token that made this link was revoked")
    return ViewGrant(job_id, token_id, "link", float(payload["exp"]))
