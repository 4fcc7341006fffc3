"""``Idempotency-Key``: a retried creation returns the first response instead of a duplicate.

The first request with a key claims it inside its own transaction (a row unique per organisation
and key) and stores its response there, so the record and the objects it created commit
together or not at all.  A retry with the same request gets the stored status and body; the same
key with a different request is a 422.  Records are kept indefinitely.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from typing import Any

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app.db.models import IdempotencyRecord
from app.services.auth import Principal
from app.services.errors import ValidationFailedError
from app.services.scoping import scoped

MAX_KEY_LENGTH = 200
PENDING_STATUS = 0
"""Status stored while the claiming transaction is still building its response."""


@dataclass(frozen=True)
class StoredResponse:
    """A response of a creating request: status code and JSON body."""

    status_code: int
    body: dict[str, Any]


def validate_key(key: str | None) -> str | None:
    """The key, checked (1 to 200 printable ASCII characters), or None when absent."""
    if key is None:
        return None
    if not 1 <= len(key) <= MAX_KEY_LENGTH or not all(32 < ord(char) < 127 for char in key):
        raise ValidationFailedError(
            f"Idempotency-Key must be 1 to {MAX_KEY_LENGTH} printable ASCII characters "
            "without spaces (a UUID is a good choice)",
            code="invalid_idempotency_key",
        )
    return key


def request_fingerprint(method: str, path: str, parameters: dict[str, Any]) -> str:
    """SHA-256 of the method, path and canonical JSON of everything that defines the request."""
    canonical = json.dumps(
        {"method": method.upper(), "path": path, "parameters": parameters},
        sort_keys=True,
        separators=(",", ":"),
        default=str,
    )
    return hashlib.sha256(canonical.encode()).hexdigest()


def _replay(record: IdempotencyRecord, fingerprint: str) -> StoredResponse:
    if record.request_fingerprint != fingerprint:
        raise ValidationFailedError(
            "this Idempotency-Key was already used for a different request; "
            "use a new key for a new request",
            code="idempotency_key_reused",
        )
    return StoredResponse(status_code=record.status_code, body=dict(record.response_body))


def find_response(
    session: Session, principal: Principal, key: str, fingerprint: str
) -> StoredResponse | None:
    """The stored response for ``key`` (422 if it was for another request), or None."""
    record = session.scalar(
        scoped(select(IdempotencyRecord).where(IdempotencyRecord.key == key), principal)
    )
    if record is None or record.status_code == PENDING_STATUS:
        return None
    return _replay(record, fingerprint)


def claim(
    session: Session, principal: Principal, key: str, fingerprint: str
) -> tuple[IdempotencyRecord | None, StoredResponse | None]:
    """Claim ``key`` in this transaction: ``(record, None)``, or ``(None, stored)`` to replay.

    The claim is a row insert in a savepoint: a concurrent claimer waits for the winner's
    commit (PostgreSQL) or for its turn (SQLite's ``BEGIN IMMEDIATE``) and then replays.
    """
    stored = find_response(session, principal, key, fingerprint)
    if stored is not None:
        return None, stored
    record = IdempotencyRecord(
        organisation_id=principal.organisation_id,
        key=key,
        request_fingerprint=fingerprint,
        status_code=PENDING_STATUS,
        response_body={},
    )
    try:
        with session.begin_nested():
            session.add(record)
            session.flush()
    except IntegrityError:
        stored = find_response(session, principal, key, fingerprint)
        if stored is None:
            raise
        return None, stored
    return record, None


def claim_request(
    session: Session,
    principal: Principal,
    idempotency_key: str | None,
    path: str,
    parameters: dict[str, Any],
) -> tuple[IdempotencyRecord | None, StoredResponse | None]:
    """Check and claim the key of ``POST path`` with these ``parameters``: ``(None, None)``
    without a key, else :func:`claim`'s ``(record, None)`` or ``(None, stored)``."""
    key = validate_key(idempotency_key)
    if key is None:
        return None, None
    return claim(session, principal, key, request_fingerprint("POST", path, parameters))


def remember(record: IdempotencyRecord | None, response: StoredResponse) -> StoredResponse:
    """Store ``response`` on a claimed record (no-op without a key); returns ``response``."""
    if record is not None:
        record.status_code = response.status_code
        record.response_body = response.body
    return response
