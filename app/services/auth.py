"""API tokens: creation, authentication and roles.

A token is a random secret shown once; only its SHA-256 is stored.  It belongs to an
organisation and has a role: ``reader`` (read only), ``writer`` (read and write), ``admin``
(everything a writer can, and managing the organisation's tokens from the command line).
Tokens are never logged.

Authenticated tokens are cached per process for the ``token_cache_seconds`` setting (default
:data:`TOKEN_CACHE_SECONDS`; a status poll otherwise paid a database round trip just to learn
who is calling); see :class:`TokenCache` for what a revocation costs.  Operators list and revoke
tokens with ``scandiff token list`` / ``scandiff token revoke`` (:func:`list_tokens`,
:func:`revoke_existing_token`).
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
from datetime import datetime
from pathlib import Path

from sqlalchemy import ColumnElement, event, select, update
from sqlalchemy.dialects.postgresql import insert as postgresql_insert
from sqlalchemy.dialects.sqlite import insert as sqlite_insert
from sqlalchemy.orm import Session

from app.clock import iso_utc, utc_now
from app.config import DEFAULT_TOKEN_CACHE_SECONDS
from app.db.models import ApiToken, Organisation, new_id
from app.kit.data_layout import DataLayout
from app.services.errors import (
    AuthenticationError,
    ConflictError,
    NotFoundError,
    PermissionDeniedError,
    ValidationFailedError,
)

logger = logging.getLogger("scandiff.services.auth")

ROLES = ("reader", "writer", "admin")
"""Roles from least to most privileged."""

TOKEN_PREFIX = "sdt_"

TOKEN_CACHE_SECONDS = DEFAULT_TOKEN_CACHE_SECONDS
"""How long an API process trusts a token it authenticated without reading its row again: the
bound on how long a token revoked behind the service's back (plain SQL) keeps working; 0
disables the cache.  The default of the ``token_cache_seconds`` setting
(``SCANDIFF_TOKEN_CACHE_SECONDS``), which :func:`configure_token_cache` applies at API start."""
TOKEN_CACHE_MAX_ENTRIES = 4096
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


def insert_organisation_if_absent(session: Session, name: str) -> tuple[Organisation, bool]:
    """The organisation called ``name`` and whether this call created it.

    Safe when several processes create the same organisation at once (replicas starting
    together on a fresh database): the row is inserted with ``ON CONFLICT DO NOTHING`` on
    PostgreSQL and SQLite alike, so the loser of the race finds the winner's row instead of
    failing on ``uq_organisation_name``.  On PostgreSQL the conflicting insert waits for the
    winner's commit and the re-read (a new statement, a new snapshot in READ COMMITTED) sees it;
    SQLite transactions are serialised by the engine's ``BEGIN IMMEDIATE``.
    """
    name = name.strip()
    if not name or len(name) > 200:
        raise ValidationFailedError("organisation name must be 1 to 200 characters")
    organisation = session.scalar(select(Organisation).where(Organisation.name == name))
    if organisation is not None:
        return organisation, False
    dialect = session.get_bind().dialect.name
    insert = postgresql_insert if dialect == "postgresql" else sqlite_insert
    inserted = session.execute(
        insert(Organisation)
        .values(id=new_id(), name=name, created_at=utc_now())
        .on_conflict_do_nothing(index_elements=[Organisation.name])
        .returning(Organisation.id)
    ).scalar_one_or_none()
    organisation = session.scalar(
        select(Organisation)
        .where(Organisation.name == name)
        .execution_options(populate_existing=True)
    )
    if organisation is None:  # pragma: no cover - the conflict means the row exists
        raise ConflictError(f"organisation {name!r} could not be created; try again")
    return organisation, inserted is not None


def get_or_create_organisation(session: Session, name: str) -> Organisation:
    """The organisation called ``name``, created if it does not exist (race-safe)."""
    return insert_organisation_if_absent(session, name)[0]


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
    return DataLayout(data_dir).revocations_file


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


def configure_token_cache(ttl_seconds: float) -> None:
    """Set this process's token cache TTL (the ``token_cache_seconds`` setting; 0 disables it)."""
    if not 0 <= ttl_seconds < float("inf"):
        raise ValueError(f"token cache TTL must be a finite number >= 0, got {ttl_seconds!r}")
    token_cache.ttl = ttl_seconds
    token_cache.clear()


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
        .values(revoked_at=utc_now())
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


@dataclass(frozen=True)
class TokenSummary:
    """What an operator may see of a token: never the secret nor its digest."""

    id: str
    organisation: str
    role: str
    name: str | None
    created_at: datetime
    revoked_at: datetime | None

    def to_json_dict(self) -> dict[str, str | None]:
        """The summary as JSON-ready values (times as ISO 8601 UTC)."""
        return {
            "id": self.id,
            "organisation": self.organisation,
            "role": self.role,
            "name": self.name,
            "created_at": iso_utc(self.created_at),
            "revoked_at": iso_utc(self.revoked_at) if self.revoked_at else None,
        }


def _summaries(session: Session, *conditions: ColumnElement[bool]) -> list[TokenSummary]:
    rows = session.execute(
        select(ApiToken, Organisation.name)
        .join(Organisation, Organisation.id == ApiToken.organisation_id)
        .where(*conditions)
        .order_by(Organisation.name, ApiToken.created_at, ApiToken.id)
    ).all()
    return [
        TokenSummary(
            id=token.id,
            organisation=organisation_name,
            role=token.role,
            name=token.name,
            created_at=token.created_at,
            revoked_at=token.revoked_at,
        )
        for token, organisation_name in rows
    ]


def list_tokens(session: Session, organisation_name: str | None = None) -> list[TokenSummary]:
    """Every token (of ``organisation_name`` if given), by organisation then age."""
    if organisation_name is None:
        return _summaries(session)
    organisation_id = session.scalar(
        select(Organisation.id).where(Organisation.name == organisation_name.strip())
    )
    if organisation_id is None:
        raise NotFoundError(f"no organisation named {organisation_name!r}")
    return _summaries(session, ApiToken.organisation_id == organisation_id)


def token_id_of_secret(session: Session, token: str) -> str:
    """The id of the token whose secret is ``token``; :class:`NotFoundError` if none."""
    token = token.strip()
    if not token:
        raise ValidationFailedError("the token secret is empty")
    token_id = session.scalar(select(ApiToken.id).where(ApiToken.token_hash == hash_token(token)))
    if token_id is None:
        raise NotFoundError("no token has this secret")
    return token_id


def revoke_existing_token(
    session: Session, token_id: str, revocations: Path | None
) -> TokenSummary:
    """Revoke ``token_id`` with :func:`revoke_token`; the token as it was before.

    :class:`NotFoundError` for an unknown id, :class:`ConflictError` (code
    ``token_already_revoked``) for a token revoked before.  The latter still advances the
    revocation counter: the earlier revocation may have been made in the database alone, and
    running processes would otherwise keep accepting their cached use of it for their TTL.
    """
    found = _summaries(session, ApiToken.id == token_id)
    if not found:
        raise NotFoundError(f"no token with id {token_id!r}")
    summary = found[0]
    if summary.revoked_at is None and revoke_token(session, token_id, revocations):
        return summary
    revoked_at = session.scalar(select(ApiToken.revoked_at).where(ApiToken.id == token_id))
    record_revocation(revocations)
    since = f" (since {iso_utc(revoked_at)})" if revoked_at else ""
    raise ConflictError(f"token {token_id} is already revoked{since}", code="token_already_revoked")


def require_role(principal: Principal, role: str) -> Principal:
    """``principal`` if it has at least ``role``; :class:`PermissionDeniedError` otherwise."""
    if not principal.can(role):
        raise PermissionDeniedError(
            f"this token's role ({principal.role}) cannot do this; "
            f"{'an' if role.startswith('a') else 'a'} {role} token is needed"
        )
    return principal
