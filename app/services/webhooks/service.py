"""Webhooks of an organisation: create (secret shown once), list, delete, deliveries, test.

Creating and deleting need an admin token; reading needs any token of the organisation.  The
URL is checked (http or https, a public address unless the operator allows private ones) when
the webhook is created and again at every attempt (:mod:`app.jobs.alerts.deliveries`).  A
``mailto:`` url makes an e-mail alert (:mod:`app.jobs.alerts.mail`) when SMTP is set up.
The secret is stored as is: an HMAC key cannot be hashed, and it is not encrypted at rest.
"""

from __future__ import annotations

import secrets
from collections.abc import Sequence

from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from app.config import Settings
from app.db.events import EVENT_TYPES, TEST_EVENT_TYPE, record_event
from app.db.models import Webhook, WebhookDelivery
from app.kit.net import OutboundUrlError, check_url, is_mailto, mailto_recipients
from app.services.auth import Principal, require_role
from app.services.errors import NotFoundError, ValidationFailedError
from app.services.paging import newest_first_page
from app.services.scoping import scoped
from app.services.webhooks.schemas import WebhookCreate

SECRET_PREFIX = "whsec_"
MAX_WEBHOOKS_PER_ORGANISATION = 50


def new_secret() -> str:
    """A fresh webhook secret (256 random bits)."""
    return SECRET_PREFIX + secrets.token_urlsafe(32)


def checked_events(events: Sequence[str]) -> list[str]:
    """The event list without duplicates, in order; 422 naming an unknown one or an empty list."""
    unknown = [event for event in events if event not in EVENT_TYPES]
    if unknown:
        raise ValidationFailedError(
            f"unknown event type(s) {', '.join(map(repr, unknown))}; "
            f"valid: {', '.join(EVENT_TYPES)}",
            code="invalid_events",
        )
    if not events:
        raise ValidationFailedError(
            f"events is empty; name at least one of {', '.join(EVENT_TYPES)}",
            code="invalid_events",
        )
    return list(dict.fromkeys(events))


def create_webhook(
    session: Session, settings: Settings, principal: Principal, payload: WebhookCreate
) -> tuple[Webhook, str]:
    """Create a webhook (admin); the row and its secret, which is shown only now."""
    require_role(principal, "admin")
    try:
        if is_mailto(payload.url):
            if not settings.smtp_host:
                raise OutboundUrlError(
                    "e-mail alerts are not set up on this service (the operator sets "
                    "SCANDIFF_SMTP_HOST); use an http(s) url"
                )
            mailto_recipients(payload.url)
        else:
            check_url(payload.url, allow_private=settings.allow_private_addresses)
    except OutboundUrlError as exc:
        raise ValidationFailedError(f"url: {exc}", code="invalid_url") from exc
    events = checked_events(payload.events)
    existing = session.scalars(scoped(select(Webhook.id), principal)).all()
    if len(existing) >= MAX_WEBHOOKS_PER_ORGANISATION:
        raise ValidationFailedError(
            f"an organisation may have at most {MAX_WEBHOOKS_PER_ORGANISATION} webhooks; "
            "delete one first",
            code="too_many_webhooks",
        )
    secret = new_secret()
    webhook = Webhook(
        organisation_id=principal.organisation_id,
        url=payload.url,
        events=events,
        secret=secret,
        description=payload.description,
        created_by_token_id=principal.token_id,
    )
    session.add(webhook)
    session.flush()
    return webhook, secret


def get_webhook(session: Session, principal: Principal, webhook_id: str) -> Webhook:
    """The principal's webhook ``webhook_id``; 404 when it does not exist or is another's."""
    row = session.scalar(scoped(select(Webhook).where(Webhook.id == webhook_id), principal))
    if row is None:
        raise NotFoundError(f"webhook {webhook_id} not found")
    return row


def list_webhooks(
    session: Session, principal: Principal, limit: int, cursor: str | None
) -> tuple[Sequence[Webhook], str | None]:
    """The organisation's webhooks, newest first, one page."""
    return newest_first_page(session, scoped(select(Webhook), principal), Webhook, limit, cursor)


def delete_webhook(session: Session, principal: Principal, webhook_id: str) -> None:
    """Delete a webhook (admin) with its deliveries (pending ones are never sent)."""
    require_role(principal, "admin")
    webhook = get_webhook(session, principal, webhook_id)
    session.execute(delete(WebhookDelivery).where(WebhookDelivery.webhook_id == webhook.id))
    session.delete(webhook)
    session.flush()


def list_deliveries(
    session: Session, principal: Principal, webhook_id: str, limit: int, cursor: str | None
) -> tuple[Sequence[WebhookDelivery], str | None]:
    """The webhook's deliveries, newest first, one page."""
    webhook = get_webhook(session, principal, webhook_id)
    statement = scoped(select(WebhookDelivery), principal).where(
        WebhookDelivery.webhook_id == webhook.id
    )
    return newest_first_page(session, statement, WebhookDelivery, limit, cursor)


def send_test(session: Session, principal: Principal, webhook_id: str) -> WebhookDelivery:
    """Queue a ``webhook.test`` event to this webhook only (admin); its delivery."""
    require_role(principal, "admin")
    webhook = get_webhook(session, principal, webhook_id)
    event = record_event(
        session,
        principal.organisation_id,
        TEST_EVENT_TYPE,
        {"message": "a test delivery from scandiff", "webhook_id": webhook.id},
        [webhook],
    )
    return session.scalars(
        select(WebhookDelivery).where(WebhookDelivery.event_id == event.id)
    ).one()
