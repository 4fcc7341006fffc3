"""Response body of ``GET /api/v1/uploads/{upload_id}`` (a resumable upload's state)."""

from __future__ import annotations

from typing import Any

from app.services.schemas import RowRead, UtcDatetime


class ResumableUploadRead(RowRead):
    """A resumable upload: its progress, state and, once completed, the upload's answer."""

    id: str
    site_id: str
    length: int
    offset: int
    state: str
    expires_at: UtcDatetime
    created_at: UtcDatetime
    result_status: int | None
    result: dict[str, Any] | None
    """The completed upload's answer: ``{"scan": ..., "job": ...}`` as a normal upload's."""
    error: str | None
