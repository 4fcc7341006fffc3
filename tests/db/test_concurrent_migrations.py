"""API replicas starting together on an empty PostgreSQL database migrate one after the other."""

from __future__ import annotations

import threading

from app.db.migrate import current_revision, head_revision, upgrade_to_head
from app.testing.topology import (
    POSTGRES_ADMIN_URL,
    admin_url_for,
    create_database,
    drop_database,
    postgres_reachable,
)
from tests.helpers.environment import require

REPLICAS = 4


def test_replicas_migrating_an_empty_postgresql_database_at_once_all_succeed() -> None:
    require(postgres_reachable(), f"PostgreSQL not reachable at {POSTGRES_ADMIN_URL}")
    name = create_database()
    url = admin_url_for(name).replace("postgresql://", "postgresql+psycopg://", 1)
    errors: list[BaseException] = []
    start = threading.Barrier(REPLICAS)

    def replica() -> None:
        start.wait()
        try:
            upgrade_to_head(url)
        except BaseException as exc:  # a collision is what this test is about
            errors.append(exc)

    try:
        threads = [threading.Thread(target=replica) for _ in range(REPLICAS)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(120)
        assert errors == []
        assert current_revision(url) == head_revision()
    finally:
        drop_database(name)
