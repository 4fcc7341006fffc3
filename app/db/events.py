"""Events of an organisation's sites and jobs, published inside the caller's transaction.

One entry point, :func:`publish_event`, called in the same transaction as the state change it
reports (a job's results stored, a schedule's period missed, a site gone stale), so that an
event exists exactly when its cause was committed (the transactional-outbox pattern).  Event
types: ``job.changed``, ``job.unchanged``, ``job.failed``, ``site.stale``, ``schedule.missed``.

Interim body (issue 16 is being built in parallel branches): the event is only logged.  The
webhook branch replaces it with an outbox row per event that its delivery worker reads.
"""

from __future__ import annotations

import logging
from typing import Any

from sqlalchemy.orm import Session

EVENT_TYPES = ("job.changed", "job.unchanged", "job.failed", "site.stale", "schedule.missed")

logger = logging.getLogger("scandiff.events")


def publish_event(
    session: Session, *, organisation_id: str, event_type: str, payload: dict[str, Any]
) -> None:
    """Record event ``event_type`` of ``organisation_id`` in ``session``'s transaction."""
    if event_type not in EVENT_TYPES:
        raise ValueError(f"unknown event type {event_type!r}; valid: {', '.join(EVENT_TYPES)}")
    logger.info("event %s", event_type, extra={"organisation_id": organisation_id})
