"""Keyset paging, newest first, with an opaque cursor (``created_at`` and ``id`` of a row)."""

from __future__ import annotations

import base64
import binascii
import json
from collections.abc import Sequence
from datetime import datetime
from typing import Any, TypeVar

from sqlalchemy import Select, and_, or_
from sqlalchemy.orm import Session

from app.clock import as_utc
from app.services.errors import BadRequestError

DEFAULT_LIMIT = 50
MAX_LIMIT = 200

RowT = TypeVar("RowT")


def encode_cursor(created_at: datetime, row_id: str) -> str:
    """The opaque cursor pointing just after a row."""
    payload = json.dumps([as_utc(created_at).isoformat(), row_id], separators=(",", ":"))
    return base64.urlsafe_b64encode(payload.encode()).decode().rstrip("=")


def decode_cursor(cursor: str) -> tuple[datetime, str]:
    """``(created_at, id)`` from a cursor; :class:`BadRequestError` when it is not one of ours."""
    try:
        padded = cursor + "=" * (-len(cursor) % 4)
        created_at_text, row_id = json.loads(base64.urlsafe_b64decode(padded.encode()))
        return as_utc(datetime.fromisoformat(created_at_text)), str(row_id)
    except (ValueError, TypeError, binascii.Error, UnicodeDecodeError) as exc:
        raise BadRequestError(
            "malformed cursor: pass the next_cursor of a previous page", code="bad_cursor"
        ) from exc


def newest_first_page(
    session: Session, statement: Select[Any], model: Any, limit: int, cursor: str | None
) -> tuple[Sequence[Any], str | None]:
    """One page of ``statement`` (selecting ``model`` rows) newest first, and the next cursor."""
    limit = max(1, min(limit, MAX_LIMIT))
    if cursor:
        created_at, row_id = decode_cursor(cursor)
        statement = statement.where(
            or_(
                model.created_at < created_at,
                and_(model.created_at == created_at, model.id < row_id),
            )
        )
    statement = statement.order_by(model.created_at.desc(), model.id.desc()).limit(limit + 1)
    rows = session.scalars(statement).all()
    if len(rows) <= limit:
        return rows, None
    rows = rows[:limit]
    last = rows[-1]
    return rows, encode_cursor(last.created_at, last.id)


def encode_offset_cursor(offset: int) -> str:
    """The opaque cursor of a list paged by position (a sorted list without a time key)."""
    payload = json.dumps({"offset": int(offset)}, separators=(",", ":"))
    return base64.urlsafe_b64encode(payload.encode()).decode().rstrip("=")


def decode_offset_cursor(cursor: str) -> int:
    """The position a cursor of :func:`encode_offset_cursor` points at; 400 when it is not one."""
    try:
        padded = cursor + "=" * (-len(cursor) % 4)
        offset = json.loads(base64.urlsafe_b64decode(padded.encode()))["offset"]
    except (ValueError, TypeError, KeyError, binascii.Error, UnicodeDecodeError) as exc:
        raise BadRequestError(
            "malformed cursor: pass the next_cursor of a previous page", code="bad_cursor"
        ) from exc
    if not isinstance(offset, int) or offset < 0:
        raise BadRequestError(
            "malformed cursor: pass the next_cursor of a previous page", code="bad_cursor"
        )
    return offset


def offset_page(
    session: Session, statement: Select[Any], limit: int, cursor: str | None
) -> tuple[Sequence[Any], str | None]:
    """One page of an ordered ``statement`` from the cursor's position, and the next cursor."""
    offset = decode_offset_cursor(cursor) if cursor else 0
    rows = session.scalars(statement.offset(offset).limit(limit + 1)).all()
    if len(rows) <= limit:
        return rows, None
    return rows[:limit], encode_offset_cursor(offset + limit)
