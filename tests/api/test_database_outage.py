"""PostgreSQL down: every request that needs the database is a 503 with ``Retry-After``, never a
500, and leaves no scan behind; when the database is back the service recovers by itself.

The shared PostgreSQL is never stopped: the app reaches a database of this module's own through
a TCP proxy (:class:`tests.helpers.proxy.TcpProxy`), and closing the proxy is the outage (new
connections refused, open ones cut).
"""

from __future__ import annotations

import os
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import psycopg
import pytest
from sqlalchemy import text
from sqlalchemy.engine import make_url
from sqlalchemy.exc import OperationalError

from app.config import Settings
from app.db.session import DatabaseUnavailableError, get_engine
from app.testing.files import ply_bytes
from app.testing.scenes import room_points
from app.testing.waiting import wait_until
from tests.helpers.environment import require
from tests.helpers.http import assert_error, site_with_reference, upload
from tests.helpers.proxy import TcpProxy
from tests.helpers.server import ApiServer, running_api

POSTGRES_URL_ENV = "SCANDIFF_TEST_POSTGRES_URL"
DEFAULT_SERVER = "postgresql://postgres@127.0.0.1:5432/postgres"


def server_admin_url() -> str:
    """The maintenance database of the PostgreSQL server the tests use (libpq URL)."""
    configured = os.environ.get(POSTGRES_URL_ENV)
    if not configured:
        return DEFAULT_SERVER
    url = make_url(configured).set(drivername="postgresql", database="postgres")
    return url.render_as_string(hide_password=False)


def postgres_reachable(url: str) -> bool:
    """Whether a connection to ``url`` works."""
    try:
        with psycopg.connect(url, connect_timeout=3):
            return True
    except psycopg.Error:
        return False


@pytest.fixture(scope="module")
def outage(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[ApiServer, TcpProxy]]:
    """The app on a fresh PostgreSQL database reached through an open proxy; dropped after."""
    admin_url = server_admin_url()
    require(postgres_reachable(admin_url), f"PostgreSQL not reachable at {admin_url}")
    database = f"scandiff_outage_{uuid.uuid4().hex[:10]}"
    with psycopg.connect(admin_url, autocommit=True) as connection:
        connection.execute(f'CREATE DATABASE "{database}"')
    server = make_url(admin_url)
    proxy = TcpProxy((server.host or "127.0.0.1", server.port or 5432)).open()
    url = server.set(drivername="postgresql+psycopg", host="127.0.0.1", port=proxy.port)
    settings = Settings(
        data_dir=tmp_path_factory.mktemp("outage-data"),
        database_url=url.set(database=database).render_as_string(hide_password=False),
        token_cache_seconds=0,  # every request reads its token: every request needs the database
        max_upload_bytes=400_000,
    )
    try:
        with running_api(settings) as api:
            yield api, proxy
    finally:
        proxy.close()
        get_engine(settings.sqlalchemy_url).dispose()
        with psycopg.connect(admin_url, autocommit=True) as connection:
            connection.execute(f'DROP DATABASE IF EXISTS "{database}" WITH (FORCE)')


@dataclass
class SiteBeforeAnOutage:
    """A writer's site with its reference, and the files stored before the outage."""

    api: ApiServer
    proxy: TcpProxy
    client: httpx.Client
    site: dict[str, Any]
    reference: dict[str, Any]
    files_before: list[Path]


@pytest.fixture
def before_outage(outage: tuple[ApiServer, TcpProxy]) -> Iterator[SiteBeforeAnOutage]:
    """A new site with a reference, the database up; the proxy is open again afterwards."""
    api, proxy = outage
    client = api.client(api.token("writer"))
    site, reference = site_with_reference(client)
    yield SiteBeforeAnOutage(api, proxy, client, site, reference, api.stored_files())
    if not proxy.is_open:
        proxy.open()


def scan_bytes(seed: int) -> bytes:
    """A 3k-point room scan as PLY."""
    return ply_bytes(room_points(3000, seed=seed))


def assert_unavailable(response: httpx.Response) -> None:
    """A 503 ``database_unavailable`` with ``Retry-After`` and a message saying what to do."""
    detail = assert_error(response, 503, "database_unavailable")
    assert response.headers["Retry-After"] == "5"
    assert detail.startswith("the database is unavailable"), detail
    assert "retry after 5 seconds" in detail


def site_scans(client: httpx.Client, site_id: str) -> list[dict[str, object]]:
    """The scans of ``site_id`` (waiting until the database answers again)."""
    response = wait_until(
        lambda: (r := client.get(f"/api/v1/sites/{site_id}/scans")).status_code == 200 and r,
        30,
        "the API answers again",
        interval=0.2,
    )
    body = response.json()
    return list(body["items"] if isinstance(body, dict) else body)


def test_requests_needing_the_database_are_503_while_it_is_down_and_work_after(
    before_outage: SiteBeforeAnOutage,
) -> None:
    api, proxy, client = before_outage.api, before_outage.proxy, before_outage.client
    site, reference, files_before = (
        before_outage.site,
        before_outage.reference,
        before_outage.files_before,
    )

    proxy.close()
    assert_unavailable(client.get("/api/v1/sites"))
    assert_unavailable(client.post("/api/v1/sites", json={"name": "during-the-outage"}))
    assert_unavailable(client.get(f"/api/v1/sites/{site['id']}/scans"))
    assert_unavailable(upload(client, site["id"], scan_bytes(2), method="pca"))
    assert api.stored_files() == files_before  # no half-written scan
    health = client.get("/api/v1/health")
    assert health.status_code == 503 and health.json()["database"]["status"] == "error"

    proxy.open()
    assert [scan["id"] for scan in site_scans(client, site["id"])] == [reference["id"]]
    accepted = upload(client, site["id"], scan_bytes(3), method="pca")
    assert accepted.status_code == 202, accepted.text
    assert len(site_scans(client, site["id"])) == 2
    assert client.get("/api/v1/health").status_code == 200


def test_an_outage_during_an_upload_leaves_no_scan(before_outage: SiteBeforeAnOutage) -> None:
    api, proxy, client, site = (
        before_outage.api,
        before_outage.proxy,
        before_outage.client,
        before_outage.site,
    )
    body = scan_bytes(4)

    def body_cut_by_an_outage() -> Iterator[bytes]:
        yield body[: len(body) // 2]
        time.sleep(0.3)  # the server has authenticated and is streaming the body to disk
        proxy.close()
        yield body[len(body) // 2 :]

    response = client.post(
        f"/api/v1/sites/{site['id']}/scans",
        params={"filename": "scan.ply", "method": "pca"},
        content=body_cut_by_an_outage(),
        headers={"Content-Type": "application/octet-stream"},
    )
    assert_unavailable(response)
    assert api.stored_files() == before_outage.files_before

    proxy.open()
    assert len(site_scans(client, site["id"])) == 1


def test_an_unreachable_database_in_the_jobs_api_is_a_503_too(
    before_outage: SiteBeforeAnOutage,
) -> None:
    client = before_outage.client
    before_outage.proxy.close()
    assert_unavailable(client.get(f"/api/v1/jobs/{uuid.uuid4().hex}"))
    assert_unavailable(
        client.post(
            "/api/v1/jobs",
            json={"reference_scan_id": uuid.uuid4().hex, "scan_id": uuid.uuid4().hex},
        )
    )


@pytest.mark.parametrize(
    ("database", "statement", "error", "message"),
    [
        # SQLite does not create directories: the file cannot be opened (an outage).
        ("gone/scandiff.db", "SELECT 1", DatabaseUnavailableError, "unable to open database file"),
        # A statement the database refuses is a bug, not an outage.
        ("scandiff.db", "SELECT * FROM no_such_table", OperationalError, "no such table"),
    ],
)
def test_only_an_unusable_sqlite_file_is_unavailable(
    tmp_path: Path, database: str, statement: str, error: type[Exception], message: str
) -> None:
    engine = get_engine(f"sqlite:///{tmp_path / database}")
    try:
        with pytest.raises(error, match=message), engine.connect() as connection:
            connection.execute(text(statement))
    finally:
        engine.dispose()
