"""E-mail alerts: a webhook whose url is ``mailto:`` gets its events through a real local SMTP
server (aiosmtpd), sent by a real ``scandiff worker``; a 451 is retried like a webhook's 500;
without SMTP set up, a ``mailto:`` url is a 422 that says so."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from app.config import Settings
from app.testing.files import ply_bytes
from app.testing.scenes import room_points
from app.testing.waiting import wait_until
from app.testing.webhooks import WEBHOOK_SETTINGS, docs_verifier
from tests.helpers.http import assert_error, site_with_reference, upload_accepted
from tests.helpers.server import ApiServer, running_api
from tests.helpers.smtp import SmtpServer
from tests.helpers.webhooks import start_delivery_worker
from tests.helpers.worker import WorkerProcess


@pytest.fixture
def smtp_server() -> Iterator[SmtpServer]:
    with SmtpServer(fail_first=1) as server:
        yield server


@pytest.fixture
def smtp_settings(smtp_server: SmtpServer) -> dict[str, object]:
    return {
        "smtp_host": "127.0.0.1",
        "smtp_port": smtp_server.port,
        "smtp_security": "none",
        "smtp_from": "alerts@scandiff.test",
    }


@pytest.fixture
def mail_api(job_settings: Settings, smtp_settings: dict[str, object]) -> Iterator[ApiServer]:
    settings = job_settings.model_copy(update={**WEBHOOK_SETTINGS, **smtp_settings})
    with running_api(settings) as api:
        yield api


def test_a_job_event_is_e_mailed_after_a_refusal(
    mail_api: ApiServer,
    smtp_server: SmtpServer,
    smtp_settings: dict[str, object],
    worker_factory: Callable[..., WorkerProcess],
) -> None:
    admin = mail_api.client(mail_api.token("admin"))
    created = admin.post(
        "/api/v1/webhooks",
        json={"url": "mailto:ops@example.com,lead@example.com", "events": ["job.changed"]},
    )
    assert created.status_code == 201, created.text
    webhook = created.json()
    start_delivery_worker(worker_factory, mail_api, **smtp_settings)
    site, _ = site_with_reference(admin)
    job_id = upload_accepted(
        admin,
        site["id"],
        "scan.ply",
        ply_bytes(room_points(3000, seed=2) + np.array([2.0, 0.0, 0.0])),
    )["job"]["id"]

    [message] = smtp_server.wait_for_messages(1)
    assert smtp_server.refused == 1
    assert smtp_server.recipients == [["ops@example.com", "lead@example.com"]]
    assert message["From"] == "alerts@scandiff.test"
    assert message["Subject"] == f"[scandiff] job.changed: {site['name']} (changed)"
    text = message.get_body(preferencelist=("plain",)).get_content()
    assert site["name"] in text and job_id in text and "/view?link=" in text
    [attachment] = list(message.iter_attachments())
    body = attachment.get_content()
    document = json.loads(body)
    assert document["id"] == message["Scandiff-Event-Id"]
    assert document["job"]["id"] == job_id and document["decision"] == "changed"
    assert docs_verifier()(webhook["secret"], message["Scandiff-Signature"], body)

    [row] = wait_until(
        lambda: [
            item
            for item in admin.get(f"/api/v1/webhooks/{webhook['id']}/deliveries").json()["items"]
            if item["status"] == "delivered"
        ],
        30,
        "the e-mail delivery recorded as delivered",
    )
    assert row["attempts"] == 2 and row["last_status_code"] == 250


def test_mailto_without_smtp_or_with_a_bad_address_is_422(job_settings: Settings) -> None:
    with running_api(job_settings) as api:
        admin = api.client(api.token("admin"))
        detail = assert_error(
            admin.post("/api/v1/webhooks", json={"url": "mailto:ops@example.com"}),
            422,
            "invalid_url",
        )
        assert "SCANDIFF_SMTP_HOST" in detail
    configured = job_settings.model_copy(update={"smtp_host": "127.0.0.1"})
    with running_api(configured) as api:
        admin = api.client(api.token("admin"))
        detail = assert_error(
            admin.post("/api/v1/webhooks", json={"url": "mailto:not-an-address"}),
            422,
            "invalid_url",
        )
        assert "not an e-mail address" in detail
