"""API tokens: creation, authentication and roles.

A token is a random secret shown once; only its SHA-256 is stored.  It belongs to an
organisation and has a role: ``reader`` (read only), ``writer`` (read and write), ``admin``
(everything a writer can, and managing the organisation's tokens from the command line).
Tokens are never logged.

Authenticated tokens are cached per process for :data:`TOKEN_CACHE_SECONDS` (a status poll
otherwise paid a database round trip just to learn who is calling); see :class:`TokenCache`
for what a revocation costs.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import os
import secrets
import threading
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from sqlalchemy import event, select, update
from sqlalchemy.orm import Session

from app.db.models import ApiToken, Organisation
from app.services.errors import AuthenticationError, PermissionDeniedError, ValidationFailedError

logger = logging.getLogger("scandiff.services.auth")

ROLES = ("reader", "writer", "admin")
"""Roles from least to most privileged."""

TOKEN_PREFIX = "sdt_"

TOKEN_CACHE_SECONDS = 5.0
"""How long an API process trusts a token it authenticated without reading its row again: the
bound on how long a token revoked behind the service's back (plain SQL) keeps working; 0
disables the cache.  (To become a setting, ``token_cache_seconds``.)"""
TOKEN_CACHE_MAX_ENTRIES = 4096
REVOCATIONS_FILE = "token-revocations"
"""In the data directory: one line appended per revocation; its size is the revocation counter
every process checks (one ``stat``) before trusting its cache."""


@dataclass(frozen=True)
class Principal:
    """Who is calling: the organisation and role of an authenticated token."""

    organisation_id: str
    role: str
    token_id: str

    def can(self, role: str) -> bool:
        """Whether this principal has at least ``role``."""
        return ROLES.index(self.role) >= ROLES.index(role)


def hash_token(token: str) -> str:
    """The SHA-256 hex digest stored for ``token``."""
    return hashlib.sha256(token.encode("utf-8", "surrogatepass")).hexdigest()


def get_or_create_organisation(session: Session, name: str) -> Organisation:
    """The organisation called ``name``, created if it does not exist."""
    name = name.strip()
    if not name or len(name) > 200:
        raise ValidationFailedError("organisation name must be 1 to 200 characters")
    organisation = session.scalar(select(Organisation).where(Organisation.name == name))
    if organisation is None:
        organisation = Organisation(name=name)
        session.add(organisation)
        session.flush()
    return organisation


def create_token(
    session: Session, organisation_name: str, role: str, name: str | None = None
) -> str:
    """Create a token for ``organisation_name`` (created if needed) and return it (shown once)."""
    if role not in ROLES:
        raise ValidationFailedError(f"role must be one of {', '.join(ROLES)}, got {role!r}")
    organisation = get_or_create_organisation(session, organisation_name)
    token = TOKEN_PREFIX + secrets.token_urlsafe(32)
    session.add(
        ApiToken(
            organisation_id=organisation.id, role=role, token_hash=hash_token(token), name=name
        )
    )
    session.flush()
    return token


def revocations_path(data_dir: Path) -> Path:
    """The revocation counter file of the service using ``data_dir``."""
    return data_dir / REVOCATIONS_FILE


def revocation_counter(path: Path | None) -> int:
    """The revocation counter: the size of ``path`` (-1 when there is none)."""
    if path is None:
        return -1
    try:
        return os.stat(path).st_size
    except OSError:
        return -1


@dataclass(frozen=True)
class _CacheEntry:
    principal: Principal
    expires_at: float
    counter: int


class TokenCache:
    """Token digest (never the token) to principal, for ``ttl`` seconds; failures are not cached.

    An entry is only returned for the digest it was stored under, before it expires, and while
    the revocation counter still has the value read *before* the token's row was: a revocation
    through :func:`revoke_token` (any process sharing the data directory) ends every cached use
    of every token at once; one made directly in the database is seen within ``ttl`` seconds.
    A role change is seen within ``ttl`` seconds too.
    """

    def __init__(self, ttl: float, max_entries: int) -> None:
        self.ttl = ttl
        self.max_entries = max_entries
        self._entries: dict[str, _CacheEntry] = {}
        self._lock = threading.Lock()

    def get(self, digest: str, counter: int) -> Principal | None:
        """The cached principal of ``digest`` if still valid under ``counter``."""
        entry = self._entries.get(digest)
        if entry is None:
            return None
        if entry.counter != counter or entry.expires_at <= time.monotonic():
            self._entries.pop(digest, None)
            return None
        return entry.principal

    def put(self, digest: str, principal: Principal, counter: int) -> None:
        """Remember ``principal`` for ``digest``, read while the counter was ``counter``."""
        if self.ttl <= 0:
            return
        with self._lock:
            if len(self._entries) >= self.max_entries:
                now = time.monotonic()
                self._entries = {
                    key: entry for key, entry in self._entries.items() if entry.expires_at > now
                }
                if len(self._entries) >= self.max_entries:
                    self._entries.clear()
            self._entries[digest] = _CacheEntry(principal, time.monotonic() + self.ttl, counter)

    def clear(self) -> None:
        """Forget every entry."""
        with self._lock:
            self._entries.clear()


token_cache = TokenCache(TOKEN_CACHE_SECONDS, TOKEN_CACHE_MAX_ENTRIES)
"""This process's cache, used by the API's bearer-token dependency."""


def authenticate(session: Session, token: str | None) -> Principal:
    """The principal of a bearer ``token``; :class:`AuthenticationError` if missing or invalid."""
    if not token:
        raise AuthenticationError("missing bearer token: send 'Authorization: Bearer <token>'")
    digest = hash_token(token)
    row = session.scalar(select(ApiToken).where(ApiToken.token_hash == digest))
    if row is None or row.revoked_at is not None or not hmac.compare_digest(row.token_hash, digest):
        raise AuthenticationError("invalid or revoked token")
    return Principal(organisation_id=row.organisation_id, role=row.role, token_id=row.id)


def cached_principal(token: str | None, revocations: Path | None) -> Principal | None:
    """The principal of ``token`` from :data:`token_cache` (no database), or None."""
    if not token:
        return None
    return token_cache.get(hash_token(token), revocation_counter(revocations))


def authenticate_and_cache(
    session: Session, token: str | None, revocations: Path | None
) -> Principal:
    """:func:`authenticate`, remembering a success in :data:`token_cache`."""
    counter = revocation_counter(revocations)  # before the row is read: see TokenCache
    principal = authenticate(session, token)
    token_cache.put(hash_token(token or ""), principal, counter)
    return principal


def revoke_token(session: Session, token_id: str, revocations: Path | None) -> bool:
    """Revoke token ``token_id``; once committed, every process's cached use of it ends."""
    revoked = session.execute(
        update(ApiToken)
        .where(ApiToken.id == token_id, ApiToken.revoked_at.is_(None))
        .values(revoked_at=datetime.now(UTC))
    ).rowcount
    if revoked:
        # The session event, not app.services.transaction.after_commit: it also fires for the
        # CLI's plain ``transaction()``.
        event.listen(
            session, "after_commit", lambda _session: record_revocation(revocations), once=True
        )
    return bool(revoked)


def record_revocation(revocations: Path | None) -> None:
    """Advance the revocation counter (and drop this process's cache)."""
    token_cache.clear()
    if revocations is None:
        return
    try:
        with open(revocations, "a", encoding="ascii") as counter_file:
            counter_file.write(f"{time.time():.6f}\n")
    except OSError as exc:
        logger.warning(
            "could not advance the revocation counter: other processes may accept the revoked "
            "token for up to %.0f s more (%s)",
            token_cache.ttl,
            exc,
        )


def require_role(principal: Principal, role: str) -> Principal:
    """``principal`` if it has at least ``role``; :class:`PermissionDeniedError` otherwise."""
    if not principal.can(role):
        raise PermissionDeniedError(
            f"this token's role ({principal.role}) cannot do this; a {role} token is needed"
        )
    return principal
