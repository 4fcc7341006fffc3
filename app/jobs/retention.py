"""Retention of the events outbox: events older than ``event_retention_days`` are deleted with
their webhook deliveries, once none of those deliveries is still pending or in flight.

Run by every recovery sweep, a bounded batch at a time, so a long backlog is worked off over
several sweeps without one long write lock.
"""

from __future__ import annotations

from datetime import datetime, timedelta

from sqlalchemy import delete, exists, select

from app.config import Settings
from app.db.models import DeliveryStatus, Event, WebhookDelivery
from app.db.session import transaction

PRUNE_BATCH = 500
"""Events deleted per sweep at most."""


def prune_events(settings: Settings, now: datetime, batch: int = PRUNE_BATCH) -> int:
    """Delete up to ``batch`` expired events whose deliveries are all final; how many."""
    cutoff = now - timedelta(days=settings.event_retention_days)
    unfinished = exists().where(
        WebhookDelivery.event_id == Event.id,
        WebhookDelivery.status.in_([DeliveryStatus.PENDING, DeliveryStatus.DELIVERING]),
    )
    with transaction(settings.sqlalchemy_url) as session:
        expired = session.scalars(
            select(Event.id).where(Event.created_at < cutoff, ~unfinished).limit(batch)
        ).all()
        if not expired:
            return 0
        session.execute(delete(WebhookDelivery).where(WebhookDelivery.event_id.in_(expired)))
        session.execute(delete(Event).where(Event.id.in_(expired)))
    return len(expired)
