"""Alembic migrations: upgrade an empty database, downgrade to base, agree with the models."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from sqlalchemy import create_engine, inspect

from app.db.migrate import current_revision, downgrade_to_base, head_revision, upgrade_to_head
from app.db.models import Base
from tests.helpers.environment import require

PROJECT_ROOT = Path(__file__).resolve().parents[2]


def sqlite_url(path: Path) -> str:
    return f"sqlite:///{path}"


def table_names(url: str) -> set[str]:
    engine = create_engine(url)
    try:
        return set(inspect(engine).get_table_names())
    finally:
        engine.dispose()


def test_upgrade_head_on_an_empty_database_creates_every_table(tmp_path: Path) -> None:
    url = sqlite_url(tmp_path / "nested" / "fresh.sqlite3")
    upgrade_to_head(url)
    assert current_revision(url) == head_revision()
    assert table_names(url) == set(Base.metadata.tables) | {"alembic_version"}


def test_downgrade_base_removes_everything_and_upgrade_again_works(tmp_path: Path) -> None:
    url = sqlite_url(tmp_path / "db.sqlite3")
    upgrade_to_head(url)
    downgrade_to_base(url)
    assert current_revision(url) is None
    assert table_names(url) <= {"alembic_version"}
    upgrade_to_head(url)
    assert current_revision(url) == head_revision()


def test_models_and_migrations_agree(tmp_path: Path) -> None:
    url = sqlite_url(tmp_path / "db.sqlite3")
    upgrade_to_head(url)
    engine = create_engine(url)
    try:
        with engine.connect() as connection:
            context = MigrationContext.configure(connection, opts={"compare_type": True})
            differences = compare_metadata(context, Base.metadata)
    finally:
        engine.dispose()
    assert differences == []


def test_alembic_command_line_takes_the_url_from_x_argument(tmp_path: Path) -> None:
    url = sqlite_url(tmp_path / "cli.sqlite3")
    alembic = [sys.executable, "-m", "alembic", "-c", str(PROJECT_ROOT / "alembic.ini")]
    subprocess.run(
        [*alembic, "-x", f"url={url}", "upgrade", "head"],
        check=True,
        capture_output=True,
        cwd=PROJECT_ROOT,
    )
    assert current_revision(url) == head_revision()


POSTGRES_URL_ENV = "SCANDIFF_TEST_POSTGRES_URL"


def test_migrations_on_postgresql() -> None:
    require(
        bool(os.environ.get(POSTGRES_URL_ENV)),
        f"set {POSTGRES_URL_ENV}=postgresql+psycopg://user@host:port/empty_db to run "
        "(.ci/run creates one)",
    )
    url = os.environ[POSTGRES_URL_ENV]
    downgrade_to_base(url)
    upgrade_to_head(url)
    assert current_revision(url) == head_revision()
    engine = create_engine(url)
    try:
        with engine.connect() as connection:
            context = MigrationContext.configure(connection, opts={"compare_type": True})
            assert compare_metadata(context, Base.metadata) == []
    finally:
        engine.dispose()
    downgrade_to_base(url)
    assert current_revision(url) is None
    upgrade_to_head(url)
