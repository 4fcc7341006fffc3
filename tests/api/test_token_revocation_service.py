"""Revoking a token while the real service runs (``scandiff serve`` in its own processes).

The API process caches every token it authenticated for ``SCANDIFF_TOKEN_CACHE_SECONDS``.
``scandiff token revoke`` (another process) must end a cached token's use from the very next
request whatever that TTL; a revocation made behind the service's back (plain SQL) is only seen
when the cached entry expires: never before the TTL, and at once with the cache disabled (0).
"""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Callable

import httpx
from sqlalchemy import select, update

from app.clock import utc_now
from app.config import Settings
from app.db.models import ApiToken
from app.db.session import transaction
from app.services.auth import TOKEN_CACHE_SECONDS, create_token, hash_token
from app.testing.paths import PROJECT_ROOT
from app.testing.service import ServiceProcess
from tests.helpers.http import unique_name

ServiceFactory = Callable[..., ServiceProcess]
EXPIRY_DEADLINE_SECONDS = 60.0
"""Generous bound for a 1 s TTL to be seen expiring (the test asserts semantics, not speed)."""


def scandiff(service: ServiceProcess, *arguments: str) -> subprocess.CompletedProcess[str]:
    """``python -m app ARGUMENTS --data-dir <the service's>`` in its own process."""
    return subprocess.run(
        [sys.executable, "-m", "app", *arguments, "--data-dir", str(service.data_dir)],
        cwd=PROJECT_ROOT,
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=120,
    )


def issue_listed_token(service: ServiceProcess, organisation: str | None = None) -> tuple[str, str]:
    """A writer token of ``organisation`` (default: a new one) and its id: (secret, id).

    Issued in this process on the service's database (``scandiff token create`` and ``list`` as
    subprocesses are tests/cli/test_token_cli.py's subject); only the revocations here run the
    command, from another process than the service's.
    """
    with transaction(Settings(data_dir=service.data_dir).sqlalchemy_url) as session:
        secret = create_token(session, organisation or unique_name("revoke-org"), "writer")
        token_id = session.execute(
            select(ApiToken.id).where(ApiToken.token_hash == hash_token(secret))
        ).scalar_one()
    return secret, str(token_id)


def issue_token(service: ServiceProcess) -> str:
    """A writer token of a new organisation (see :func:`issue_listed_token`)."""
    secret, _ = issue_listed_token(service)
    return secret


def authenticated_and_cached(service: ServiceProcess, secret: str) -> httpx.Client:
    """A client whose token the API process has authenticated (and so cached)."""
    client = service.client(secret)
    for _ in range(2):  # the first reads the token's row, the second is served from the cache
        assert client.get("/api/v1/sites").status_code == 200
    return client


def revoke_in_database(service: ServiceProcess, secret: str) -> None:
    """Revoke behind the service's back: plain SQL, no revocation counter."""
    with transaction(Settings(data_dir=service.data_dir).sqlalchemy_url) as session:
        session.execute(
            update(ApiToken)
            .where(ApiToken.token_hash == hash_token(secret))
            .values(revoked_at=utc_now())
        )


def assert_unauthorized(response: httpx.Response) -> None:
    assert response.status_code == 401, response.text
    assert response.json()["error"] == "unauthorized"


def test_cli_revocation_ends_a_cached_token_at_once_whatever_the_ttl(
    service_factory: ServiceFactory,
) -> None:
    service = service_factory(workers=0, env={"SCANDIFF_TOKEN_CACHE_SECONDS": "3600"})

    secret, token_id = issue_listed_token(service)
    bystander_secret = issue_token(service)
    client = authenticated_and_cached(service, secret)
    bystander = authenticated_and_cached(service, bystander_secret)
    revoked = scandiff(service, "token", "revoke", token_id)
    assert revoked.returncode == 0, revoked.stderr
    assert f"revoked token {token_id}" in revoked.stderr
    assert_unauthorized(client.get("/api/v1/sites"))  # the very next request
    assert bystander.get("/api/v1/sites").status_code == 200  # other tokens keep working

    # Behind the service's back the hour-long cache keeps the token alive, past the default TTL.
    secret, token_id = issue_listed_token(service)
    client = authenticated_and_cached(service, secret)
    revoke_in_database(service, secret)
    assert client.get("/api/v1/sites").status_code == 200
    time.sleep(TOKEN_CACHE_SECONDS + 0.5)
    assert client.get("/api/v1/sites").status_code == 200, "the 3600 s setting was not applied"
    # The operator's revoke says it was already revoked, and still ends the cached use.
    again = scandiff(service, "token", "revoke", token_id)
    assert again.returncode == 2
    assert f"token {token_id} is already revoked" in again.stderr
    assert_unauthorized(client.get("/api/v1/sites"))


def test_a_database_only_revocation_is_seen_when_a_short_ttl_expires(
    service_factory: ServiceFactory,
) -> None:
    service = service_factory(workers=0, env={"SCANDIFF_TOKEN_CACHE_SECONDS": "1"})
    secret = issue_token(service)
    client = authenticated_and_cached(service, secret)
    revoke_in_database(service, secret)
    deadline = time.monotonic() + EXPIRY_DEADLINE_SECONDS
    while (response := client.get("/api/v1/sites")).status_code == 200:
        assert time.monotonic() < deadline, "a revoked token outlived a 1 s cache"
        time.sleep(0.1)
    assert_unauthorized(response)
    for _ in range(3):  # and it stays refused: failures are never cached as successes
        assert_unauthorized(client.get("/api/v1/sites"))


def test_a_zero_ttl_disables_the_cache(
    service_factory: ServiceFactory,
) -> None:
    service = service_factory(workers=0, env={"SCANDIFF_TOKEN_CACHE_SECONDS": "0"})
    secret = issue_token(service)
    client = authenticated_and_cached(service, secret)
    revoke_in_database(service, secret)
    assert_unauthorized(client.get("/api/v1/sites"))
