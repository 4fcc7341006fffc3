"""Events of an organisation's sites and jobs, published inside the caller's transaction.

One entry point, :func:`publish_event`, called in the same transaction as the state change it
reports (a job's results stored, a schedule's period missed, a site gone stale), so that an
event exists exactly when its cause was committed (the transactional-outbox pattern).  Event
types: ``job.changed``, ``job.unchanged``, ``job.failed``, ``site.stale``, ``schedule.missed``.

It adds an :class:`~app.db.models.Event` row (its id is the event id receivers use to drop
duplicates) and one ``pending`` :class:`~app.db.models.WebhookDelivery` per webhook of the
organisation subscribed to the type; the workers deliver them (:mod:`app.jobs.alerts.deliveries`).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.clock import utc_now
from app.db.models import DeliveryStatus, Event, Webhook, WebhookDelivery

EVENT_TYPES = ("job.changed", "job.unchanged", "job.failed", "site.stale", "schedule.missed")
TEST_EVENT_TYPE = "webhook.test"
"""The type of the event ``POST /api/v1/webhooks/{id}/test`` sends (to that webhook only)."""
DEFAULT_MAX_ATTEMPTS = 8

logger = logging.getLogger("scandiff.events")


def publish_event(
    session: Session,
    *,
    organisation_id: str,
    event_type: str,
    payload: dict[str, Any],
) -> Event:
    """Record event ``event_type`` of ``organisation_id`` in ``session``'s transaction."""
    if event_type not in EVENT_TYPES:
        raise ValueError(f"unknown event type {event_type!r}; valid: {', '.join(EVENT_TYPES)}")
    webhooks = session.scalars(
        select(Webhook).where(Webhook.organisation_id == organisation_id)
    ).all()
    subscribed = [webhook for webhook in webhooks if event_type in (webhook.events or [])]
    event = record_event(session, organisation_id, event_type, payload, subscribed)
    logger.info(
        "event %s",
        event_type,
        extra={
            "organisation_id": organisation_id,
            "event_id": event.id,
            "deliveries": len(subscribed),
        },
    )
    return event


def record_event(
    session: Session,
    organisation_id: str,
    event_type: str,
    payload: dict[str, Any],
    webhooks: Iterable[Webhook],
) -> Event:
    """Add the event row and a pending delivery to each of ``webhooks``; the event."""
    now = utc_now()
    event = Event(organisation_id=organisation_id, type=event_type, payload=payload, created_at=now)
    session.add(event)
    session.flush()
    session.add_all(
        WebhookDelivery(
            organisation_id=organisation_id,
            webhook_id=webhook.id,
            event_id=event.id,
            event_type=event_type,
            status=DeliveryStatus.PENDING,
            attempts=0,
            max_attempts=DEFAULT_MAX_ATTEMPTS,  # the worker's setting replaces it at claim
            next_attempt_at=now,
            created_at=now,
        )
        for webhook in webhooks
    )
    session.flush()
    return event
