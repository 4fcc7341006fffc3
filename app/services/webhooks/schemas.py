"""Request and response bodies of the webhook routes (``/api/v1/webhooks``)."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, Field, StringConstraints

from app.services.schemas import RowRead, StrictBody, UtcDatetime

DEFAULT_EVENTS = ("job.changed", "job.failed", "site.stale", "schedule.missed")
"""The events of a webhook created without ``events`` (``job.unchanged`` is opt-in)."""


class WebhookCreate(StrictBody):
    """A new webhook: where to POST, which events, and an optional description."""

    url: Annotated[str, StringConstraints(strip_whitespace=True, min_length=1, max_length=2000)] = (
        Field(description="http(s) URL that receives the events (public addresses only).")
    )
    events: list[Annotated[str, StringConstraints(strip_whitespace=True, max_length=64)]] = Field(
        default_factory=lambda: list(DEFAULT_EVENTS),
        max_length=16,
        description="Event types: job.changed, job.unchanged (opt-in), job.failed, site.stale, "
        "schedule.missed. Default: all but job.unchanged.",
    )
    description: Annotated[str, StringConstraints(max_length=200)] | None = None


class WebhookRead(RowRead):
    """A webhook as the API shows it (never with its secret, except once: ``WebhookCreated``)."""

    id: str
    url: str
    events: list[str]
    description: str | None
    created_at: UtcDatetime


class WebhookCreated(WebhookRead):
    """The answer to creating a webhook: the only time its secret is shown."""

    secret: str = Field(description="Signs every delivery (Scandiff-Signature); shown once.")


class DeliveryRead(RowRead):
    """One event's delivery to a webhook: where it is, how its last attempt went."""

    id: str
    webhook_id: str
    event_id: str
    event_type: str
    status: str
    attempts: int
    max_attempts: int
    last_status_code: int | None
    last_error: str | None
    next_attempt_at: UtcDatetime | None
    last_attempt_at: UtcDatetime | None
    delivered_at: UtcDatetime | None
    created_at: UtcDatetime


class DeliveryPage(BaseModel):
    """One page of deliveries, newest first; pass ``next_cursor`` as ``cursor`` for the next."""

    items: list[DeliveryRead]
    next_cursor: str | None
