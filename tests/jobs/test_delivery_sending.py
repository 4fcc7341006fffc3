"""One delivery attempt and the claims, in this process against real local receivers and a
migrated SQLite file: redirects are never followed, an address that became private is not
called, a receiver that does not answer times out, backoff grows and is capped with jitter,
and deliveries claimed by racing senders reach the receiver exactly once each (no crash)."""

from __future__ import annotations

import random
import threading
from typing import Any

from sqlalchemy import select

from app.config import Settings
from app.db.events import publish_event
from app.db.models import Job, Webhook, WebhookDelivery
from app.db.session import transaction
from app.jobs.alerts.deliveries import (
    ClaimedDelivery,
    backoff_seconds,
    claim_next_delivery,
    deliver_due,
    send_attempt,
)
from app.jobs.recovery import recovery_sweep
from app.testing.webhooks import WEBHOOK_SETTINGS, WebhookReceiver, organisation_with_webhook
from tests.helpers.jobs import create_job


def delivery_to(url: str, secret: str = "whsec_test") -> ClaimedDelivery:
    return ClaimedDelivery(
        id="d" * 32,
        attempt=1,
        max_attempts=3,
        lease_owner="test",
        url=url,
        secret=secret,
        event_id="e" * 32,
        event_type="webhook.test",
        body=b'{"id": "eeee"}',
    )


def local_settings(job_settings: Settings, **changes: Any) -> Settings:
    return job_settings.model_copy(update={**WEBHOOK_SETTINGS, **changes})


def test_redirects_are_not_followed(job_settings: Settings) -> None:
    settings = local_settings(job_settings)
    with WebhookReceiver() as target, WebhookReceiver(redirect_to=target.url) as redirecting:
        redirecting.secret = "whsec_test"
        outcome = send_attempt(delivery_to(redirecting.url), settings)
        assert outcome.status_code == 307 and not outcome.delivered
        assert "redirects are not followed" in (outcome.error or "")
        assert len(redirecting.received) == 1
        assert target.received == []


def test_a_private_address_is_not_called_unless_allowed(job_settings: Settings) -> None:
    with WebhookReceiver() as receiver:
        receiver.secret = "whsec_test"
        refused = send_attempt(
            delivery_to(receiver.url),
            local_settings(job_settings, allow_private_addresses=False),
        )
        assert refused.status_code is None and "non-public address 127.0.0.1" in refused.error
        assert receiver.received == []
        allowed = send_attempt(delivery_to(receiver.url), local_settings(job_settings))
        assert allowed.delivered and len(receiver.accepted()) == 1


def test_a_receiver_that_does_not_answer_times_out(job_settings: Settings) -> None:
    with WebhookReceiver(hold_first=1) as receiver:
        receiver.secret = "whsec_test"
        outcome = send_attempt(
            delivery_to(receiver.url), local_settings(job_settings, webhook_timeout_seconds=0.5)
        )
    assert outcome.status_code is None and not outcome.delivered
    assert "timed out" in (outcome.error or "")


def test_backoff_doubles_is_capped_and_jittered() -> None:
    rng = random.Random(3)
    for attempt in range(1, 12):
        nominal = min(100.0, 2.0 * 2 ** (attempt - 1))
        delays = [backoff_seconds(attempt, 2.0, 100.0, rng) for _ in range(50)]
        assert all(nominal / 2 <= delay <= nominal for delay in delays)
        assert len(set(delays)) > 1  # jitter: not all the same


def test_racing_senders_deliver_each_event_exactly_once(job_settings: Settings) -> None:
    settings = local_settings(job_settings)
    events = 30
    with WebhookReceiver() as receiver:
        receiver.secret = "whsec_race"
        with transaction(settings.sqlalchemy_url) as session:
            organisation_id = organisation_with_webhook(
                session, "race", receiver.url, receiver.secret, ["schedule.missed"]
            )
            for number in range(events):
                publish_event(
                    session,
                    organisation_id=organisation_id,
                    event_type="schedule.missed",
                    payload={"period": number},
                )
        senders = [
            threading.Thread(target=deliver_due, args=(settings,), kwargs={"limit": events})
            for _ in range(4)
        ]
        for sender in senders:
            sender.start()
        for sender in senders:
            sender.join(60)
        assert claim_next_delivery(settings, "late-owner") is None  # nothing left due
    ids = [delivery.event_id for delivery in receiver.received]
    assert len(ids) == events and len(set(ids)) == events
    assert all(delivery.signature_valid for delivery in receiver.received)
    with transaction(settings.sqlalchemy_url) as session:
        rows = session.scalars(select(WebhookDelivery)).all()
        assert {(row.status, row.attempts) for row in rows} == {("delivered", 1)}


def test_a_job_given_up_by_the_recovery_sweep_publishes_job_failed(
    job_settings: Settings,
) -> None:
    job_id = create_job(job_settings, max_attempts=1)
    with transaction(job_settings.sqlalchemy_url) as session:
        job = session.get_one(Job, job_id)
        session.add(
            Webhook(
                organisation_id=job.organisation_id,
                url="https://93.184.215.14/hook",
                events=["job.failed"],
                secret="whsec_test",
            )
        )
        job.status = "running"
        job.attempts = 1
        job.lease_owner = "gone-host:1:dead"
        job.lease_expires_at = None  # the lease is over: the worker is lost
    recovery_sweep(job_settings)
    with transaction(job_settings.sqlalchemy_url) as session:
        assert session.get_one(Job, job_id).status == "failed"
        [delivery] = session.scalars(select(WebhookDelivery)).all()
        assert delivery.event_type == "job.failed" and delivery.status == "pending"
