"""Webhook deliveries end to end: the real API (HTTP, migrated SQLite), real ``scandiff worker``
processes delivering to a real local HTTP receiver that checks every signature with the snippet
of ``docs/webhooks.md``.

* A finished job's event arrives signed, with site, job, score, threshold, decision, regions and
  a working view link; the receiver fails the first attempts on purpose and sees the retries
  arrive with the same event id until one is accepted; the deliveries route tells the story.
* A worker SIGKILLed while the receiver holds a delivery: once a worker runs again, the event
  is delivered (same event id).
* The docs' verification snippet accepts real deliveries and refuses tampering and replays.
"""

from __future__ import annotations

import os
import signal
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from app.config import Settings
from app.testing.files import ply_bytes
from app.testing.scenes import room_points
from app.testing.waiting import wait_until
from app.testing.webhooks import WEBHOOK_SETTINGS, WebhookReceiver, docs_verifier
from tests.helpers.http import site_with_reference, upload_accepted
from tests.helpers.server import ApiServer, running_api
from tests.helpers.webhooks import start_delivery_worker
from tests.helpers.worker import WorkerProcess


@pytest.fixture
def webhook_api(job_settings: Settings) -> Iterator[ApiServer]:
    """The API on the job settings plus fast webhook retries and local receivers allowed."""
    settings = job_settings.model_copy(update=WEBHOOK_SETTINGS)
    with running_api(settings) as api:
        yield api


def create_webhook(admin: httpx.Client, receiver: WebhookReceiver, events: list[str]) -> str:
    """Register ``receiver`` for ``events``; remember the secret shown once; the webhook id."""
    response = admin.post("/api/v1/webhooks", json={"url": receiver.url, "events": events})
    assert response.status_code == 201, response.text
    created = response.json()
    receiver.secret = created["secret"]
    return str(created["id"])


def deliveries(admin: httpx.Client, webhook_id: str) -> list[dict[str, Any]]:
    response = admin.get(f"/api/v1/webhooks/{webhook_id}/deliveries")
    assert response.status_code == 200, response.text
    return list(response.json()["items"])


def test_job_event_is_retried_until_accepted_with_one_event_id(
    webhook_api: ApiServer, worker_factory: Callable[..., WorkerProcess]
) -> None:
    fail_first = 2
    with WebhookReceiver(fail_first=fail_first) as receiver:
        admin = webhook_api.client(webhook_api.token("admin"))
        webhook_id = create_webhook(admin, receiver, ["job.changed", "job.unchanged", "job.failed"])
        start_delivery_worker(worker_factory, webhook_api)
        site, _ = site_with_reference(admin)
        job_id = upload_accepted(
            admin, site["id"], "scan.ply", ply_bytes(room_points(3000, seed=2))
        )["job"]["id"]

        received = receiver.wait_for_accepted(1)
        job = admin.get(f"/api/v1/jobs/{job_id}").json()

    assert [delivery.answered for delivery in received] == [500] * fail_first + [200]
    assert all(delivery.signature_valid for delivery in received)
    assert len({delivery.event_id for delivery in received}) == 1
    attempts = [delivery.headers["scandiff-delivery-attempt"] for delivery in received]
    assert attempts == [str(number) for number in range(1, fail_first + 2)]

    body = received[-1].json()
    assert body["id"] == received[-1].event_id
    assert body["type"] == ("job.changed" if job["changed"] else "job.unchanged")
    assert body["site"] == {"id": site["id"], "name": site["name"]}
    assert body["job"]["id"] == job_id and body["job"]["status"] == "succeeded"
    assert body["score"] == pytest.approx(job["score"])
    assert body["threshold"] == pytest.approx(job["threshold"])
    assert body["decision"] == ("changed" if job["changed"] else "unchanged")
    assert body["regions"]["count"] == job["n_regions"]

    # The view link opens the job's 3D view without a token; a tampered one does not.
    link = body["view_link"]["url"]
    assert link.startswith(f"{webhook_api.base_url}/jobs/{job_id}/view?link=")
    with httpx.Client(timeout=60) as anonymous:
        assert anonymous.get(link[:-3] + "AAA").status_code == 403
        assert anonymous.get(link).status_code == 200

    [row] = deliveries(admin, webhook_id)
    assert row["status"] == "delivered"
    assert row["attempts"] == fail_first + 1
    assert row["last_status_code"] == 200
    assert row["event_id"] == body["id"] and row["event_type"] == body["type"]


def test_gives_up_after_max_attempts(
    webhook_api: ApiServer, worker_factory: Callable[..., WorkerProcess]
) -> None:
    max_attempts = 3
    with WebhookReceiver(fail_first=100) as receiver:
        admin = webhook_api.client(webhook_api.token("admin"))
        webhook_id = create_webhook(admin, receiver, ["job.failed"])
        start_delivery_worker(worker_factory, webhook_api, webhook_max_attempts=max_attempts)
        test = admin.post(f"/api/v1/webhooks/{webhook_id}/test")
        assert test.status_code == 202, test.text
        assert test.json()["status"] == "pending"

        row = wait_until(
            lambda: next(
                (r for r in deliveries(admin, webhook_id) if r["status"] == "failed"), None
            ),
            60,
            "the delivery failed for good",
        )
    assert row["attempts"] == max_attempts
    assert row["last_status_code"] == 500
    assert row["next_attempt_at"] is None
    assert len(receiver.received) == max_attempts
    assert {delivery.headers["scandiff-event-type"] for delivery in receiver.received} == {
        "webhook.test"
    }


def test_worker_killed_during_a_delivery_delivers_after_restart(
    webhook_api: ApiServer, worker_factory: Callable[..., WorkerProcess], tmp_path: Path
) -> None:
    with WebhookReceiver(hold_first=1) as receiver:
        admin = webhook_api.client(webhook_api.token("admin"))
        webhook_id = create_webhook(admin, receiver, ["job.changed"])
        worker = start_delivery_worker(worker_factory, webhook_api)
        assert admin.post(f"/api/v1/webhooks/{webhook_id}/test").status_code == 202
        wait_until(receiver.held.is_set, 60, "the first attempt reached the receiver")
        [row] = deliveries(admin, webhook_id)
        assert row["status"] == "delivering" and row["attempts"] == 1

        os.killpg(worker.process.pid, signal.SIGKILL)  # the worker and all its processes
        worker.process.wait(10)
        start_delivery_worker(worker_factory, webhook_api)

        received = receiver.wait_for_accepted(1)
        [row] = wait_until(
            lambda: [r for r in deliveries(admin, webhook_id) if r["status"] == "delivered"],
            30,
            "the delivery recorded as delivered",
        )
    assert len(received) == 2
    assert received[0].answered is None and received[1].answered == 200
    assert received[0].event_id == received[1].event_id
    assert all(delivery.signature_valid for delivery in received)
    assert row["attempts"] == 2


def test_docs_snippet_refuses_tampering_and_replays(
    webhook_api: ApiServer, worker_factory: Callable[..., WorkerProcess]
) -> None:
    verify = docs_verifier()
    with WebhookReceiver() as receiver:
        admin = webhook_api.client(webhook_api.token("admin"))
        webhook_id = create_webhook(admin, receiver, ["job.changed"])
        start_delivery_worker(worker_factory, webhook_api)
        assert admin.post(f"/api/v1/webhooks/{webhook_id}/test").status_code == 202
        [delivery] = receiver.wait_for_accepted(1)

    header = delivery.headers["scandiff-signature"]
    assert verify(receiver.secret, header, delivery.body)
    assert not verify(receiver.secret, header, delivery.body + b" ")
    assert not verify("whsec_another", header, delivery.body)
    assert not verify(receiver.secret, header, delivery.body, tolerance=-1)  # too old
    assert not verify(receiver.secret, "v1=" + header.split("v1=")[1], delivery.body)
