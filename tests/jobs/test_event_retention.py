"""The recovery sweep deletes events past their retention with their deliveries, never one
whose delivery is still pending or in flight, and never a recent one."""

from __future__ import annotations

from datetime import timedelta

from sqlalchemy import func, select

from app.clock import utc_now
from app.config import Settings
from app.db.events import publish_event
from app.db.models import DeliveryStatus, Event, Organisation, WebhookDelivery
from app.db.session import transaction
from app.jobs.recovery import recovery_sweep
from app.jobs.retention import prune_events
from app.testing.webhooks import organisation_with_webhook


def test_old_events_with_final_deliveries_are_pruned(job_settings: Settings) -> None:
    settings = job_settings.model_copy(update={"event_retention_days": 7})
    statuses = [
        DeliveryStatus.DELIVERED,
        DeliveryStatus.FAILED,
        DeliveryStatus.PENDING,
        DeliveryStatus.DELIVERING,
    ]
    with transaction(settings.sqlalchemy_url) as session:
        organisation_id = organisation_with_webhook(
            session, "retention", "https://93.184.215.14/hook", "whsec_test", ["schedule.missed"]
        )
        events = {}
        for age_days in (30, 3):
            for status in statuses:
                event = publish_event(
                    session,
                    organisation_id=organisation_id,
                    event_type="schedule.missed",
                    payload={"age_days": age_days, "status": str(status)},
                )
                event.created_at = utc_now() - timedelta(days=age_days)
                session.flush()
                delivery = session.scalars(
                    select(WebhookDelivery).where(WebhookDelivery.event_id == event.id)
                ).one()
                delivery.status = status
                events[(age_days, status)] = event.id
    report = recovery_sweep(settings)
    assert report.pruned_events == 2
    with transaction(settings.sqlalchemy_url) as session:
        left = set(session.scalars(select(Event.id)).all())
        delivery_events = set(session.scalars(select(WebhookDelivery.event_id)).all())
    pruned = {events[(30, DeliveryStatus.DELIVERED)], events[(30, DeliveryStatus.FAILED)]}
    assert left == set(events.values()) - pruned
    assert delivery_events == left  # the deliveries went with their events, no others
    assert prune_events(settings, utc_now()) == 0  # nothing more is due


def test_pruning_works_in_bounded_batches(job_settings: Settings) -> None:
    with transaction(job_settings.sqlalchemy_url) as session:
        organisation = Organisation(name="batches")
        session.add(organisation)
        session.flush()
        for _ in range(7):
            event = publish_event(
                session, organisation_id=organisation.id, event_type="site.stale", payload={}
            )
            event.created_at = utc_now() - timedelta(days=400)
    later = utc_now()
    assert [prune_events(job_settings, later, batch=3) for _ in range(4)] == [3, 3, 1, 0]
    with transaction(job_settings.sqlalchemy_url) as session:
        assert session.scalar(select(func.count()).select_from(Event)) == 0
