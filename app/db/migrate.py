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
from sqlalchemy import Engine, create_engine
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


def upgrade_to_head(url: str) -> None:
    """Bring the database at ``url`` to the newest revision (creating a SQLite file if needed)."""
    command.upgrade(alembic_config(url), "head")


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
