"""Apply the Alembic migrations programmatically (``scandiff serve`` and ``token`` do).

The scripts live in ``migrations/`` at the project root (shipped in the wheel as
``app/migrations``); ``alembic.ini`` there serves the ``alembic`` command line.  Migrations on
SQLite run with ``foreign_keys=OFF``: batch migrations recreate tables, and dropping a parent
table with foreign keys on would cascade-delete its children's rows.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import Engine, create_engine, text
from sqlalchemy.engine import make_url

from app.db.session import make_engine

MIGRATIONS_DIR = (Path(__file__).resolve().parents[1] / "migrations").resolve()
"""``app/migrations``: in a checkout a symlink to the top-level ``migrations/``; in an installed
wheel the scripts themselves, shipped as package data."""


def alembic_config(url: str) -> Config:
    """An Alembic config for ``url`` pointing at the project's migration scripts."""
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    config.attributes["url"] = url
    return config


def migration_engine(url: str) -> Engine:
    """An engine for running migrations: on SQLite, WAL, busy timeout, BEGIN IMMEDIATE, no FKs."""
    if not url.startswith("sqlite"):
        return create_engine(url)
    database = make_url(url).database
    if database and database != ":memory:":
        Path(database).expanduser().parent.mkdir(parents=True, exist_ok=True)
    return make_engine(url, foreign_keys=False)


MIGRATION_LOCK_KEY = 0x5CA4D1FF
"""PostgreSQL advisory-lock key held while migrating: API replicas starting together take turns."""


def upgrade_to_head(url: str) -> None:
    """Bring the database at ``url`` to the newest revision (creating a SQLite file if needed).

    On PostgreSQL the upgrade holds an advisory lock, so replicas starting at once on an empty
    database migrate one after the other (the later ones find it at head) instead of colliding.
    SQLite needs none: Alembic's transaction there is ``BEGIN IMMEDIATE``-serialised.
    """
    config = alembic_config(url)
    if not url.startswith("postgresql"):
        command.upgrade(config, "head")
        return
    engine = migration_engine(url)
    try:
        with engine.connect() as connection:
            connection.execute(text("SELECT pg_advisory_lock(:key)"), {"key": MIGRATION_LOCK_KEY})
            try:
                command.upgrade(config, "head")
            finally:
                connection.execute(
                    text("SELECT pg_advisory_unlock(:key)"), {"key": MIGRATION_LOCK_KEY}
                )
                connection.commit()
    finally:
        engine.dispose()


def downgrade_to_base(url: str) -> None:
    """Undo every migration of the database at ``url``."""
    command.downgrade(alembic_config(url), "base")


@lru_cache(maxsize=1)
def head_revision() -> str | None:
    """The newest revision of the migration scripts (read once per process)."""
    return ScriptDirectory.from_config(alembic_config("sqlite://")).get_current_head()


def current_revision(url: str) -> str | None:
    """The revision the database at ``url`` is at (None when it was never migrated)."""
    engine = migration_engine(url)
    try:
        with engine.connect() as connection:
            return MigrationContext.configure(connection).get_current_revision()
    finally:
        engine.dispose()
