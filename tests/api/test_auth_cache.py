"""The per-process token cache (app.services.auth.TokenCache) behind the bearer dependency.

What it must never do: answer for another token (and so another organisation), remember a
failure, or keep accepting a revoked token longer than documented: at once after
``auth.revoke_token``, within ``TokenCache.ttl`` after a revocation made in the database alone.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from pydantic import ValidationError
from sqlalchemy import update

from app.clock import utc_now
from app.config import Settings
from app.db.models import ApiToken
from app.db.session import transaction
from app.main import create_app
from app.services import auth
from app.services.auth import Principal, TokenCache, hash_token
from tests.helpers.http import assert_error, create_site, unique_name
from tests.helpers.server import ApiServer

SHORT_TTL = 0.5


@pytest.fixture
def short_ttl() -> Iterator[None]:
    """The process's cache with a short TTL (the API under test runs in this process)."""
    saved = auth.token_cache.ttl
    auth.token_cache.ttl = SHORT_TTL
    auth.token_cache.clear()
    try:
        yield
    finally:
        auth.token_cache.ttl = saved
        auth.token_cache.clear()


def revoke_in_database(api: ApiServer, token: str) -> None:
    """Revoke behind the service's back (plain SQL): the revocation counter does not move."""
    with transaction(api.settings.sqlalchemy_url) as session:
        session.execute(
            update(ApiToken)
            .where(ApiToken.token_hash == hash_token(token))
            .values(revoked_at=utc_now())
        )


def token_id(api: ApiServer, token: str) -> str:
    with transaction(api.settings.sqlalchemy_url) as session:
        return auth.authenticate(session, token).token_id


def test_revoke_token_refuses_a_cached_token_at_once(api: ApiServer) -> None:
    token = api.token("writer")
    client = api.client(token)
    assert client.get("/api/v1/sites").status_code == 200
    assert client.get("/api/v1/sites").status_code == 200  # now from the cache
    with transaction(api.settings.sqlalchemy_url) as session:
        assert auth.revoke_token(
            session, token_id(api, token), auth.revocations_path(api.settings.data_dir)
        )
    assert_error(client.get("/api/v1/sites"), 401, "unauthorized")


def test_revocation_counter_of_another_process_ends_cached_tokens(api: ApiServer) -> None:
    """Another process (a CLI) revoking advances the counter file: this process sees it."""
    token = api.token("writer")
    client = api.client(token)
    assert client.get("/api/v1/sites").status_code == 200
    revoke_in_database(api, token)
    # What record_revocation does in the revoking process, minus clearing *our* cache.
    with open(auth.revocations_path(api.settings.data_dir), "a", encoding="ascii") as counter:
        counter.write("1\n")
    assert_error(client.get("/api/v1/sites"), 401, "unauthorized")


def test_database_only_revocation_is_refused_within_the_ttl(
    api: ApiServer, short_ttl: None
) -> None:
    token = api.token("writer")
    client = api.client(token)
    assert client.get("/api/v1/sites").status_code == 200
    revoke_in_database(api, token)
    revoked_at = time.monotonic()
    while True:
        # The request's start counts, not its end: under load a request that began inside the
        # TTL may answer after it, and rightly from the cache.
        sent_at = time.monotonic()
        if client.get("/api/v1/sites").status_code != 200:
            break
        assert sent_at - revoked_at <= SHORT_TTL + 0.2, "still accepted after the TTL"
        time.sleep(0.05)
    assert_error(client.get("/api/v1/sites"), 401, "unauthorized")


def test_cached_principals_never_cross_organisations(api: ApiServer) -> None:
    """Tokens of two organisations used in turn: each only ever sees its own objects."""
    token_a = api.token("writer", unique_name("cache-org-a"))
    token_b = api.token("writer", unique_name("cache-org-b"))
    client_a, client_b = api.client(token_a), api.client(token_b)
    site_a = create_site(client_a)
    site_b = create_site(client_b)
    for _ in range(20):
        assert client_a.get(f"/api/v1/sites/{site_a['id']}").status_code == 200
        assert_error(client_b.get(f"/api/v1/sites/{site_a['id']}"), 404)
        assert client_b.get(f"/api/v1/sites/{site_b['id']}").status_code == 200
        assert_error(client_a.get(f"/api/v1/sites/{site_b['id']}"), 404)
        ids_a = {site["id"] for site in client_a.get("/api/v1/sites").json()["items"]}
        assert site_a["id"] in ids_a and site_b["id"] not in ids_a


def test_cache_is_keyed_by_digest_and_never_remembers_failures(api: ApiServer) -> None:
    cache = TokenCache(ttl=60.0, max_entries=8)
    principal = Principal(organisation_id="org-a", role="admin", token_id="t-a")
    cache.put(hash_token("sdt_a"), principal, counter=0)
    assert cache.get(hash_token("sdt_a"), counter=0) == principal
    assert cache.get(hash_token("sdt_b"), counter=0) is None
    assert cache.get(hash_token("sdt_a"), counter=1) is None  # a revocation happened
    assert cache.get(hash_token("sdt_a"), counter=0) is None  # and the entry is gone

    auth.token_cache.clear()
    unknown = "sdt_" + unique_name("never-issued")
    with (
        transaction(api.settings.sqlalchemy_url) as session,
        pytest.raises(auth.AuthenticationError),
    ):
        auth.authenticate_and_cache(session, unknown, None)
    assert auth.cached_principal(unknown, None) is None


def test_cache_expires_and_stays_bounded() -> None:
    cache = TokenCache(ttl=0.05, max_entries=4)
    for index in range(10):
        cache.put(f"digest-{index}", Principal("org", "reader", f"t{index}"), counter=-1)
        assert len(cache._entries) <= 4
    cache.put("digest-x", Principal("org", "reader", "tx"), counter=-1)
    assert cache.get("digest-x", counter=-1) is not None
    time.sleep(0.06)
    assert cache.get("digest-x", counter=-1) is None
    assert TokenCache(ttl=0.0, max_entries=4).get("digest-x", counter=-1) is None


def test_token_cache_seconds_defaults_to_the_constant_and_reads_the_environment(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.delenv("SCANDIFF_TOKEN_CACHE_SECONDS", raising=False)
    assert Settings().token_cache_seconds == auth.TOKEN_CACHE_SECONDS
    monkeypatch.setenv("SCANDIFF_TOKEN_CACHE_SECONDS", "0")
    assert Settings().token_cache_seconds == 0.0
    monkeypatch.setenv("SCANDIFF_TOKEN_CACHE_SECONDS", "1.5")
    assert Settings().token_cache_seconds == 1.5
    description = Settings.model_fields["token_cache_seconds"].description or ""
    assert "0 disables" in description and "scandiff token revoke" in description


@pytest.mark.parametrize("value", ["-1", "-0.5", "nan", "inf"])
def test_a_negative_or_non_finite_token_cache_ttl_is_rejected_clearly(
    value: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("SCANDIFF_TOKEN_CACHE_SECONDS", value)
    with pytest.raises(ValidationError, match="token_cache_seconds must be a finite number"):
        Settings()


def test_the_cli_reports_a_bad_token_cache_ttl_without_a_traceback(tmp_path: Path) -> None:
    completed = subprocess.run(
        [sys.executable, "-m", "app", "token", "list", "--data-dir", str(tmp_path)],
        env={**os.environ, "SCANDIFF_TOKEN_CACHE_SECONDS": "-1"},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert completed.returncode == 2
    assert "Traceback" not in completed.stderr
    assert completed.stderr.startswith("scandiff: error: invalid settings: token_cache_seconds ")
    assert "SCANDIFF_TOKEN_CACHE_SECONDS" in completed.stderr and ">= 0" in completed.stderr


def test_create_app_applies_token_cache_seconds_to_the_process_cache(tmp_path: Path) -> None:
    saved = auth.token_cache.ttl
    try:
        create_app(Settings(data_dir=tmp_path, token_cache_seconds=0))
        assert auth.token_cache.ttl == 0
        auth.token_cache.put("digest", Principal("org", "reader", "t"), counter=-1)
        assert auth.token_cache.get("digest", counter=-1) is None  # 0 disables the cache
        create_app(Settings(data_dir=tmp_path, token_cache_seconds=42))
        assert auth.token_cache.ttl == 42
    finally:
        auth.token_cache.ttl = saved
        auth.token_cache.clear()
