"""Webhooks over HTTP: create (secret once), list, read, delete, roles, bad input (422 saying
what to fix), unknown and other organisations' ids (404), deliveries paged, test deliveries.

The module's server keeps the default: private and loopback addresses refused.  No consumer
runs here, so deliveries stay ``pending`` (their sending is ``tests/jobs/test_webhook_delivery``).
"""

from __future__ import annotations

import httpx
import pytest

from app.db.models import Event, WebhookDelivery
from app.testing.files import ply_bytes
from app.testing.scenes import room_points
from tests.helpers.database import count_rows
from tests.helpers.http import assert_error, site_with_reference, unique_name, upload_accepted
from tests.helpers.jobs import finish_job
from tests.helpers.server import ApiServer

PUBLIC_URL = "https://93.184.215.14/hooks/scandiff"
"""A public IP literal: passes the address check without DNS."""


@pytest.fixture
def organisation() -> str:
    return unique_name("org")


@pytest.fixture
def admin(api: ApiServer, organisation: str) -> httpx.Client:
    return api.client(api.token("admin", organisation))


def create(admin: httpx.Client, **body: object) -> dict:
    response = admin.post("/api/v1/webhooks", json={"url": PUBLIC_URL, **body})
    assert response.status_code == 201, response.text
    return response.json()


def test_create_shows_the_secret_once_and_lists_without_it(admin: httpx.Client) -> None:
    created = create(admin, description="ops channel")
    assert created["secret"].startswith("whsec_") and len(created["secret"]) > 40
    assert created["events"] == ["job.changed", "job.failed", "site.stale", "schedule.missed"]
    assert created["url"] == PUBLIC_URL and created["description"] == "ops channel"

    read = admin.get(f"/api/v1/webhooks/{created['id']}").json()
    assert "secret" not in read
    assert read == {key: value for key, value in created.items() if key != "secret"}
    listed = admin.get("/api/v1/webhooks").json()
    assert [item["id"] for item in listed["items"]] == [created["id"]]
    assert all("secret" not in item for item in listed["items"])
    assert create(admin)["secret"] != created["secret"]


def test_job_unchanged_is_opt_in_and_duplicates_collapse(admin: httpx.Client) -> None:
    created = create(admin, events=["job.unchanged", "job.changed", "job.unchanged"])
    assert created["events"] == ["job.unchanged", "job.changed"]


@pytest.mark.parametrize(
    ("body", "error", "words"),
    [
        ({"url": "ftp://93.184.215.14/x"}, "invalid_url", "http or https"),
        ({"url": "javascript:alert(1)"}, "invalid_url", "http or https"),
        ({"url": "http://127.0.0.1:9000/hook"}, "invalid_url", "non-public address 127.0.0.1"),
        ({"url": "http://10.1.2.3/hook"}, "invalid_url", "non-public address 10.1.2.3"),
        ({"url": "http://169.254.169.254/latest"}, "invalid_url", "non-public"),
        ({"url": "http://[::1]/hook"}, "invalid_url", "non-public"),
        ({"url": "http://localhost/hook"}, "invalid_url", "loopback"),
        ({"url": "https://user:pw@93.184.215.14/"}, "invalid_url", "user name or password"),
        ({"url": PUBLIC_URL, "events": ["job.exploded"]}, "invalid_events", "job.exploded"),
        ({"url": PUBLIC_URL, "events": []}, "invalid_events", "at least one"),
        ({"events": ["job.changed"]}, "validation_error", "url"),
        ({"url": PUBLIC_URL, "colour": "red"}, "validation_error", "colour"),
    ],
)
def test_bad_bodies_are_422_saying_what_to_fix(
    admin: httpx.Client, body: dict, error: str, words: str
) -> None:
    detail = assert_error(admin.post("/api/v1/webhooks", json=body), 422, error)
    assert words in detail
    assert admin.get("/api/v1/webhooks").json()["items"] == []


def test_roles_admin_creates_and_deletes_others_read(api: ApiServer, organisation: str) -> None:
    admin = api.client(api.token("admin", organisation))
    writer = api.client(api.token("writer", organisation))
    reader = api.client(api.token("reader", organisation))
    assert_error(writer.post("/api/v1/webhooks", json={"url": PUBLIC_URL}), 403)
    webhook = create(admin)
    assert reader.get(f"/api/v1/webhooks/{webhook['id']}").status_code == 200
    assert reader.get(f"/api/v1/webhooks/{webhook['id']}/deliveries").status_code == 200
    assert_error(writer.delete(f"/api/v1/webhooks/{webhook['id']}"), 403)
    assert_error(writer.post(f"/api/v1/webhooks/{webhook['id']}/test"), 403)
    assert admin.delete(f"/api/v1/webhooks/{webhook['id']}").status_code == 204
    assert_error(admin.get(f"/api/v1/webhooks/{webhook['id']}"), 404)


def test_unknown_and_other_organisations_ids_are_404(api: ApiServer, admin: httpx.Client) -> None:
    theirs = create(api.client(api.token("admin")))
    for webhook_id in (theirs["id"], "0" * 32):
        assert_error(admin.get(f"/api/v1/webhooks/{webhook_id}"), 404, "not_found")
        assert_error(admin.delete(f"/api/v1/webhooks/{webhook_id}"), 404, "not_found")
        assert_error(admin.get(f"/api/v1/webhooks/{webhook_id}/deliveries"), 404, "not_found")
        assert_error(admin.post(f"/api/v1/webhooks/{webhook_id}/test"), 404, "not_found")
    assert all(item["id"] != theirs["id"] for item in admin.get("/api/v1/webhooks").json()["items"])


def test_test_deliveries_are_listed_newest_first_in_pages(admin: httpx.Client) -> None:
    webhook = create(admin)
    sent = []
    for _ in range(3):
        response = admin.post(f"/api/v1/webhooks/{webhook['id']}/test")
        assert response.status_code == 202, response.text
        sent.append(response.json())
    assert {delivery["status"] for delivery in sent} == {"pending"}
    assert {delivery["event_type"] for delivery in sent} == {"webhook.test"}
    assert len({delivery["event_id"] for delivery in sent}) == 3

    first = admin.get(f"/api/v1/webhooks/{webhook['id']}/deliveries", params={"limit": 2}).json()
    second = admin.get(
        f"/api/v1/webhooks/{webhook['id']}/deliveries",
        params={"limit": 2, "cursor": first["next_cursor"]},
    ).json()
    assert second["next_cursor"] is None
    listed = [item["id"] for item in first["items"] + second["items"]]
    assert listed == [delivery["id"] for delivery in reversed(sent)]
    row = first["items"][0]
    assert row["attempts"] == 0 and row["last_status_code"] is None
    assert row["next_attempt_at"] is not None


def test_a_finished_job_queues_one_delivery_per_subscribed_webhook(
    api: ApiServer, admin: httpx.Client
) -> None:
    changed_hook = create(admin, events=["job.changed"])
    unchanged_hook = create(admin, events=["job.unchanged"])
    both_hook = create(admin, events=["job.changed", "job.unchanged"])
    site, _ = site_with_reference(admin)
    job_id = upload_accepted(admin, site["id"], "s.ply", ply_bytes(room_points(2000, seed=3)))[
        "job"
    ]["id"]
    finish_job(api, job_id, 3000, 2000, changed=True)

    def delivered_types(webhook: dict) -> list[str]:
        items = admin.get(f"/api/v1/webhooks/{webhook['id']}/deliveries").json()["items"]
        return [item["event_type"] for item in items]

    assert delivered_types(changed_hook) == ["job.changed"]
    assert delivered_types(unchanged_hook) == []
    assert delivered_types(both_hook) == ["job.changed"]
    [event_id] = {
        item["event_id"]
        for webhook in (changed_hook, both_hook)
        for item in admin.get(f"/api/v1/webhooks/{webhook['id']}/deliveries").json()["items"]
    }
    assert count_rows(api, Event, id=event_id) == 1
    assert count_rows(api, WebhookDelivery, event_id=event_id) == 2
