"""Where jobs finish, their event is written in the same transaction (the outbox):
``job.failed`` when a job fails for good (an error, attempts used up, a dead worker's last
attempt), none while it is only requeued; one pending delivery per subscribed webhook."""

from __future__ import annotations

from typing import Any

from sqlalchemy import select

from app.config import Settings
from app.db.models import Event, Job, Webhook, WebhookDelivery
from app.db.session import transaction
from app.jobs.leases import claim_job, fail_job, make_lease_owner, release_job
from tests.helpers.jobs import create_job


def subscribe(settings: Settings, job_id: str, events: list[str]) -> str:
    """A webhook of the job's organisation for ``events``; its id."""
    with transaction(settings.sqlalchemy_url) as session:
        job = session.get_one(Job, job_id)
        webhook = Webhook(
            organisation_id=job.organisation_id,
            url="https://93.184.215.14/hook",
            events=events,
            secret="whsec_test",
        )
        session.add(webhook)
        session.flush()
        return webhook.id


def events_of(settings: Settings, job_id: str) -> list[tuple[str, dict[str, Any]]]:
    with transaction(settings.sqlalchemy_url) as session:
        rows = session.scalars(select(Event).order_by(Event.created_at)).all()
        return [(row.type, row.payload) for row in rows if row.payload["job"]["id"] == job_id]


def deliveries_of(settings: Settings, webhook_id: str) -> list[str]:
    with transaction(settings.sqlalchemy_url) as session:
        rows = session.scalars(
            select(WebhookDelivery).where(WebhookDelivery.webhook_id == webhook_id)
        ).all()
        return [row.event_type for row in rows]


def test_a_failed_job_publishes_job_failed_with_its_error(job_settings: Settings) -> None:
    job_id = create_job(job_settings)
    failed_hook = subscribe(job_settings, job_id, ["job.failed"])
    changed_hook = subscribe(job_settings, job_id, ["job.changed"])
    job = claim_job(job_id, job_settings, make_lease_owner())
    assert job is not None
    assert fail_job(job, job_settings, "the scan file is not a point cloud")

    [(event_type, payload)] = events_of(job_settings, job_id)
    assert event_type == "job.failed"
    assert payload["job"]["status"] == "failed"
    assert payload["job"]["error"] == "the scan file is not a point cloud"
    assert payload["decision"] is None and payload["score"] is None
    assert payload["site"]["id"] and payload["regions"]["count"] == 0
    assert deliveries_of(job_settings, failed_hook) == ["job.failed"]
    assert deliveries_of(job_settings, changed_hook) == []


def test_a_requeued_job_publishes_nothing_until_its_attempts_are_used_up(
    job_settings: Settings,
) -> None:
    job_id = create_job(job_settings, max_attempts=2)
    for attempt in (1, 2):
        job = claim_job(job_id, job_settings, make_lease_owner())
        assert job is not None and job.attempt == attempt
        status = release_job(job, job_settings, "boom", count_attempt=True)
        if attempt == 1:
            assert status == "queued"
            assert events_of(job_settings, job_id) == []
    assert status == "failed"
    [(event_type, payload)] = events_of(job_settings, job_id)
    assert event_type == "job.failed"
    assert "boom" in payload["job"]["error"]
