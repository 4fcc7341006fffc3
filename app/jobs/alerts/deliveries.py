"""Webhook deliveries: at-least-once, durable, claimed with a lease like jobs.

Every event a webhook subscribes to has a ``webhook_delivery`` row (written with the event by
:func:`app.db.events.publish_event`).  A worker **claims** a due row with one conditional
``UPDATE`` (``pending`` and due, or ``delivering`` with an expired lease or a lease owner that is
a dead process of this host: :func:`app.jobs.leases.lease_owner_is_dead_here`), which counts the
attempt and takes a lease (``lease_owner`` from :func:`app.jobs.leases.make_lease_owner`).  It
POSTs the signed body, then records the outcome only while the lease is still its own:

* a 2xx answer: ``delivered``;
* anything else (another status, a redirect, which is never followed, a timeout, a refused
  address): ``pending`` again, due after an exponential backoff with jitter, or ``failed`` once
  ``webhook_max_attempts`` are used.

A worker killed in the middle of an attempt leaves the row ``delivering``: the next claim takes it
over (at once on the same host, else when the lease expires), so the receiver may see an event
twice; the ``Scandiff-Event-Id`` header (the event id, the same on every attempt) lets it drop
the duplicate.

:func:`delivery_process` is the process a job consumer runs beside its job workers
(``scandiff serve`` and ``scandiff worker``), so deliveries need no extra service.
"""

from __future__ import annotations

import http.client
import json
import logging
import random
import threading
import time
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import Any

from sqlalchemy import select, update

from app.clock import as_utc, iso_utc, utc_now
from app.config import Settings
from app.db.models import DeliveryStatus, Event, Webhook, WebhookDelivery
from app.db.session import transaction
from app.jobs.alerts.mail import send_email
from app.jobs.leases import lease_owner_is_dead_here, make_lease_owner
from app.jobs.side_process import SideProcess
from app.kit.net import (
    OutboundUrlError,
    check_url,
    is_mailto,
    mailto_recipients,
    pinned_connection,
)
from app.kit.signing import signing_key, view_link_value, webhook_signature

logger = logging.getLogger("scandiff.webhooks")

USER_AGENT = "scandiff-webhooks/1"
MAX_RESPONSE_BYTES = 64 * 1024
"""Read at most this much of a receiver's answer (the body is not kept, only its status)."""
MAX_ERROR_CHARACTERS = 500
CLAIM_BATCH = 20
"""Due deliveries read per claim round (each is then claimed with its own conditional update)."""


@dataclass(frozen=True)
class ClaimedDelivery:
    """What a worker needs to send one attempt of a delivery it has claimed."""

    id: str
    attempt: int
    max_attempts: int
    lease_owner: str
    url: str
    secret: str
    event_id: str
    event_type: str
    body: bytes


@dataclass(frozen=True)
class AttemptOutcome:
    """How an attempt went: the receiver's status code (None without an answer) and why not."""

    status_code: int | None
    error: str | None

    @property
    def delivered(self) -> bool:
        """Whether the receiver took it (a 2xx answer)."""
        return self.error is None and self.status_code is not None and 200 <= self.status_code < 300
        # (an e-mail accepted by the SMTP server is 250)


def backoff_seconds(
    attempt: int, base: float, cap: float, rng: random.Random | None = None
) -> float:
    """Delay after failed attempt ``attempt`` (1-based): ``base * 2**(attempt-1)``, capped, times
    a random factor in [0.5, 1] (jitter, so that receivers coming back are not hit in step)."""
    delay = min(cap, base * 2 ** max(0, attempt - 1))
    return delay * (0.5 + 0.5 * (rng or random).random())


def delivery_body(event: Event, webhook: Webhook, settings: Settings) -> bytes:
    """The JSON body of a delivery: the event id and type, its payload and a view link."""
    document: dict[str, Any] = {
        "id": event.id,
        "type": event.type,
        "created_at": iso_utc(event.created_at),
        "organisation_id": event.organisation_id,
        **(event.payload or {}),
    }
    job = document.get("job")
    if isinstance(job, dict) and isinstance(job.get("id"), str) and webhook.created_by_token_id:
        value, expires_at = view_link_value(
            job["id"],
            webhook.created_by_token_id,
            signing_key(settings.secret_key, settings.data_dir),
            settings.view_link_ttl_seconds,
        )
        document["view_link"] = {
            "url": f"{settings.public_base_url}/jobs/{job['id']}/view?link={value}",
            "expires_at": iso_utc(datetime.fromtimestamp(expires_at, UTC)),
        }
    return json.dumps(document, separators=(",", ":"), sort_keys=True).encode()


def _claimable(row: WebhookDelivery, now: datetime) -> bool:
    if row.status == DeliveryStatus.PENDING:
        return True
    lease_expires_at = as_utc(row.lease_expires_at)
    return (
        lease_expires_at is None
        or lease_expires_at < now
        or lease_owner_is_dead_here(row.lease_owner)
    )


def claim_next_delivery(
    settings: Settings, owner: str, now: datetime | None = None
) -> ClaimedDelivery | None:
    """Claim one due delivery for ``owner``; None when nothing is due."""
    now = now or utc_now()
    lease_seconds = max(settings.webhook_lease_seconds, settings.webhook_timeout_seconds * 2)
    with transaction(settings.sqlalchemy_url) as session:
        # Rows in flight first (few: one per sender; those of dead senders are taken over),
        # then the pending ones that are due, oldest first.
        in_flight = session.scalars(
            select(WebhookDelivery).where(WebhookDelivery.status == DeliveryStatus.DELIVERING)
        ).all()
        due = session.scalars(
            select(WebhookDelivery)
            .where(
                WebhookDelivery.status == DeliveryStatus.PENDING,
                WebhookDelivery.next_attempt_at <= now,
            )
            .order_by(WebhookDelivery.next_attempt_at)
            .limit(CLAIM_BATCH)
        ).all()
        candidates = [*in_flight, *due]
        for row in candidates:
            if not _claimable(row, now):
                continue
            if row.attempts >= settings.webhook_max_attempts:
                _give_up(session, row, now)
                continue
            claimed = session.execute(
                update(WebhookDelivery)
                .where(
                    WebhookDelivery.id == row.id,
                    WebhookDelivery.status == row.status,
                    WebhookDelivery.attempts == row.attempts,
                )
                .values(
                    status=DeliveryStatus.DELIVERING,
                    attempts=WebhookDelivery.attempts + 1,
                    max_attempts=settings.webhook_max_attempts,
                    lease_owner=owner,
                    lease_expires_at=now + timedelta(seconds=lease_seconds),
                    last_attempt_at=now,
                )
                .execution_options(synchronize_session=False)
            ).rowcount
            if not claimed:
                continue  # another worker was faster
            event = session.get_one(Event, row.event_id)
            webhook = session.get_one(Webhook, row.webhook_id)
            return ClaimedDelivery(
                id=row.id,
                attempt=row.attempts + 1,
                max_attempts=settings.webhook_max_attempts,
                lease_owner=owner,
                url=webhook.url,
                secret=webhook.secret,
                event_id=event.id,
                event_type=event.type,
                body=delivery_body(event, webhook, settings),
            )
    return None


def _give_up(session: Any, row: WebhookDelivery, now: datetime) -> None:
    """A delivery whose last attempt died with its worker: ``failed``."""
    session.execute(
        update(WebhookDelivery)
        .where(WebhookDelivery.id == row.id, WebhookDelivery.status == row.status)
        .values(
            status=DeliveryStatus.FAILED,
            lease_owner=None,
            lease_expires_at=None,
            next_attempt_at=None,
            last_error=(
                f"gave up after {row.attempts} attempts; the last stopped without an answer "
                "(worker killed or lost)"
            ),
        )
        .execution_options(synchronize_session=False)
    )


def send_attempt(delivery: ClaimedDelivery, settings: Settings) -> AttemptOutcome:
    """POST the signed body once (or e-mail it to a ``mailto:`` url); never follows redirects;
    bounded by the timeout setting."""
    timestamp = int(time.time())
    headers = {
        "Content-Type": "application/json",
        "User-Agent": USER_AGENT,
        "Scandiff-Event-Id": delivery.event_id,
        "Scandiff-Event-Type": delivery.event_type,
        "Scandiff-Delivery-Id": delivery.id,
        "Scandiff-Delivery-Attempt": str(delivery.attempt),
        "Scandiff-Signature": webhook_signature(delivery.secret, delivery.body, timestamp),
    }
    try:
        if is_mailto(delivery.url):
            recipients = mailto_recipients(delivery.url)
            return AttemptOutcome(*send_email(recipients, delivery.body, headers, settings))
        target = check_url(delivery.url, allow_private=settings.allow_private_addresses)
    except OutboundUrlError as exc:
        return AttemptOutcome(None, f"not sent: {exc}")
    connection = pinned_connection(target, settings.webhook_timeout_seconds)
    try:
        connection.request("POST", target.path, body=delivery.body, headers=headers)
        response = connection.getresponse()
        response.read(MAX_RESPONSE_BYTES)
        status = response.status
    except (OSError, http.client.HTTPException) as exc:
        return AttemptOutcome(None, f"{type(exc).__name__}: {exc}"[:MAX_ERROR_CHARACTERS])
    finally:
        connection.close()
    if 300 <= status < 400:
        return AttemptOutcome(status, f"answered {status}: redirects are not followed")
    if not 200 <= status < 300:
        return AttemptOutcome(status, f"answered {status}")
    return AttemptOutcome(status, None)


def record_outcome(
    delivery: ClaimedDelivery, settings: Settings, outcome: AttemptOutcome
) -> str | None:
    """Store the attempt's outcome while the lease is still ours; the new status (None: lost)."""
    now = utc_now()
    values: dict[str, Any] = {
        "last_status_code": outcome.status_code,
        "last_error": outcome.error,
        "lease_owner": None,
        "lease_expires_at": None,
    }
    if outcome.delivered:
        values.update(status=DeliveryStatus.DELIVERED, delivered_at=now, next_attempt_at=None)
    elif delivery.attempt >= delivery.max_attempts:
        values.update(status=DeliveryStatus.FAILED, next_attempt_at=None)
    else:
        delay = backoff_seconds(
            delivery.attempt, settings.webhook_backoff_seconds, settings.webhook_backoff_max_seconds
        )
        values.update(status=DeliveryStatus.PENDING, next_attempt_at=now + timedelta(seconds=delay))
    with transaction(settings.sqlalchemy_url) as session:
        updated = session.execute(
            update(WebhookDelivery)
            .where(
                WebhookDelivery.id == delivery.id,
                WebhookDelivery.status == DeliveryStatus.DELIVERING,
                WebhookDelivery.lease_owner == delivery.lease_owner,
            )
            .values(**values)
            .execution_options(synchronize_session=False)
        ).rowcount
    status = str(values["status"]) if updated else None
    logger.info(
        "webhook delivery attempt",
        extra={
            "delivery_id": delivery.id,
            "event_id": delivery.event_id,
            "attempt": delivery.attempt,
            "status_code": outcome.status_code,
            "error": outcome.error,
            "status": status or "lease-lost",
        },
    )
    return status


def deliver_due(settings: Settings, owner: str | None = None, limit: int = CLAIM_BATCH) -> int:
    """Claim and send due deliveries one after the other (at most ``limit``); how many."""
    owner = owner or make_lease_owner()
    sent = 0
    while sent < limit:
        delivery = claim_next_delivery(settings, owner)
        if delivery is None:
            break
        record_outcome(delivery, settings, send_attempt(delivery, settings))
        sent += 1
    return sent


def run_delivery_loop(settings: Settings, stop: threading.Event) -> None:
    """Deliver until ``stop`` is set: right away while work is due, else every poll interval."""
    owner = make_lease_owner()
    logger.info("webhook deliveries started", extra={"lease_owner": owner})
    while not stop.is_set():
        try:
            busy = deliver_due(settings, owner) > 0
        except Exception:  # a database hiccup: log, wait, try again
            logger.exception("webhook delivery round failed")
            busy = False
        if not busy:
            stop.wait(settings.webhook_poll_seconds)


def delivery_process(settings: Settings) -> SideProcess:
    """The webhook delivery process of a job consumer (SIGTERM stops it after the attempt in
    flight), replaced when it dies."""
    return SideProcess(settings, "webhook-deliveries", run_delivery_loop)
