"""One rule for the service's own requests: every refused address class against every caller.

The callers are a webhook created over HTTP, a webhook delivery attempt (the worker's), a
schedule URL source created over HTTP and a schedule run's fetch.  Each refuses an address of
every class in ``docs/webhooks.md`` (IP literals: no DNS involved) and accepts a public one;
the module's server keeps the default (private addresses refused).
"""

from __future__ import annotations

from collections.abc import Callable

import pytest

from app.jobs.alerts.deliveries import ClaimedDelivery, send_attempt
from app.kit.net import REFUSED_ADDRESS_CLASSES
from app.services.errors import ValidationFailedError
from app.services.schedules import sources as schedule_sources
from tests.helpers.addresses import PUBLIC_HOSTS, REFUSED_HOSTS
from tests.helpers.http import assert_error, create_site
from tests.helpers.server import ApiServer

NIGHTLY = {"cron": "0 2 * * *", "timezone": "Europe/Lisbon"}


def test_every_refused_class_has_a_host_here() -> None:
    assert {name for _, name in REFUSED_HOSTS} == {name for name, _ in REFUSED_ADDRESS_CLASSES} - {
        "non-global"  # the catch-all: each address Python calls non-global has a class above
    }


def create_webhook(api: ApiServer, url: str) -> tuple[int, str]:
    """POST a webhook; the status and the error code (or ``"created"``)."""
    admin = api.client(api.token("admin"))
    response = admin.post("/api/v1/webhooks", json={"url": url})
    if response.status_code == 201:
        return 201, "created"
    detail = assert_error(response, 422, "invalid_url")
    assert "SCANDIFF_ALLOW_PRIVATE_ADDRESSES" in detail
    return 422, detail


def attempt_delivery(api: ApiServer, url: str) -> tuple[int, str]:
    """One delivery attempt to ``url`` by the worker's code, expected not to be sent; 422."""
    delivery = ClaimedDelivery(
        id="d" * 32,
        attempt=1,
        max_attempts=3,
        lease_owner="test",
        url=url,
        secret="whsec_test",
        event_id="e" * 32,
        event_type="webhook.test",
        body=b'{"id": "eeee"}',
    )
    outcome = send_attempt(delivery, api.settings)
    assert outcome.status_code is None and (outcome.error or "").startswith("not sent: ")
    return 422, outcome.error or ""


def create_url_schedule(api: ApiServer, url: str) -> tuple[int, str]:
    """POST a schedule with a URL source; the status and the detail."""
    writer = api.client(api.token("writer"))
    site = create_site(writer)
    response = writer.post(
        f"/api/v1/sites/{site['id']}/schedules", json={**NIGHTLY, "source": {"url": url}}
    )
    if response.status_code == 201:
        return 201, "created"
    return 422, assert_error(response, 422, "forbidden_url_address")


def fetch_for_a_run(api: ApiServer, url: str) -> tuple[int, str]:
    """A schedule run's fetch, refused before connecting; 201 when the check let it through."""
    try:
        schedule_sources.check_url(api.settings, url)
    except ValidationFailedError as exc:
        assert exc.code == "forbidden_url_address"
        with pytest.raises(ValidationFailedError) as fetched:
            schedule_sources.fetch_url(api.settings, url)
        assert fetched.value.code == "forbidden_url_address"
        return 422, str(exc)
    return 201, "created"


CALLERS: dict[str, Callable[[ApiServer, str], tuple[int, str]]] = {
    "webhook created": create_webhook,
    "webhook delivery": attempt_delivery,
    "schedule url source created": create_url_schedule,
    "schedule run fetch": fetch_for_a_run,
}


@pytest.mark.parametrize("caller", sorted(CALLERS))
@pytest.mark.parametrize(("host", "address_class"), REFUSED_HOSTS)
def test_every_caller_refuses_every_refused_class(
    api: ApiServer, caller: str, host: str, address_class: str
) -> None:
    status, detail = CALLERS[caller](api, f"https://{host}:8443/scan.ply")
    assert status == 422
    assert f"({address_class})" in detail


@pytest.mark.parametrize("caller", sorted(set(CALLERS) - {"webhook delivery"}))
@pytest.mark.parametrize("host", PUBLIC_HOSTS)
def test_every_caller_accepts_a_public_address(api: ApiServer, caller: str, host: str) -> None:
    # (a delivery to a public address would really be sent: its check is the same function,
    # and tests/jobs/test_delivery_sending.py sends to local receivers when they are allowed)
    assert CALLERS[caller](api, f"https://{host}/scan.ply") == (201, "created")


@pytest.mark.parametrize("caller", sorted(CALLERS))
def test_every_caller_refuses_localhost_by_name(api: ApiServer, caller: str) -> None:
    status, detail = CALLERS[caller](api, "http://localhost:8080/scan.ply")
    assert status == 422 and "loopback" in detail


def test_the_client_is_told_what_to_fix(api: ApiServer) -> None:
    writer = api.client(api.token("writer"))
    site = create_site(writer)
    response = writer.post(
        f"/api/v1/sites/{site['id']}/schedules",
        json={**NIGHTLY, "source": {"url": "http://100.64.0.1/latest.ply"}},
    )
    detail = assert_error(response, 422, "forbidden_url_address")
    assert "100.64.0.1" in detail and "SCANDIFF_ALLOW_PRIVATE_ADDRESSES=true" in detail
