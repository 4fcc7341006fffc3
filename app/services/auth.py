"""API tokens: creation, authentication and roles.

A token is a random secret shown once; only its SHA-256 is stored.  It belongs to an
organisation and has a role: ``reader`` (read only), ``writer`` (read and write), ``admin``
(everything a writer can, and managing the organisation's tokens from the command line).
Tokens are never logged.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
from dataclasses import dataclass

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.db.models import ApiToken, Organisation
from app.services.errors import AuthenticationError, PermissionDeniedError, ValidationFailedError

ROLES = ("reader", "writer", "admin")
"""Roles from least to most privileged."""

TOKEN_PREFIX = "sdt_"


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


def authenticate(session: Session, token: str | None) -> Principal:
    """The principal of a bearer ``token``; :class:`AuthenticationError` if missing or invalid."""
    if not token:
        raise AuthenticationError("missing bearer token: send 'Authorization: Bearer <token>'")
    digest = hash_token(token)
    row = session.scalar(select(ApiToken).where(ApiToken.token_hash == digest))
    if row is None or row.revoked_at is not None or not hmac.compare_digest(row.token_hash, digest):
        raise AuthenticationError("invalid or revoked token")
    return Principal(organisation_id=row.organisation_id, role=row.role, token_id=row.id)


def require_role(principal: Principal, role: str) -> Principal:
    """``principal`` if it has at least ``role``; :class:`PermissionDeniedError` otherwise."""
    if not principal.can(role):
        raise PermissionDeniedError(
            f"this token's role ({principal.role}) cannot do this; a {role} token is needed"
        )
    return principal
