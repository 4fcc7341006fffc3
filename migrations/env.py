"""Alembic environment for scandiff.

The URL comes from ``-x url=...`` on the command line, else from the caller
(:func:`app.db.migrate.upgrade_to_head` sets ``config.attributes["url"]``), else from the
scandiff Settings (``SCANDIFF_DATABASE_URL`` or the SQLite file in ``SCANDIFF_DATA_DIR``).
``render_as_batch`` makes ALTERs work on SQLite (copy-and-move tables).
"""

from __future__ import annotations

from logging.config import fileConfig

from alembic import context

from app.db.migrate import migration_engine
from app.db.models import Base

config = context.config
if config.config_file_name is not None:
    fileConfig(config.config_file_name, disable_existing_loggers=False)

target_metadata = Base.metadata


def database_url() -> str:
    """The URL to migrate: ``-x url=``, then the caller's, then the Settings'."""
    x_arguments = context.get_x_argument(as_dictionary=True)
    if x_arguments.get("url"):
        return x_arguments["url"]
    if config.attributes.get("url"):
        return str(config.attributes["url"])
    from app.config import Settings

    return Settings().sqlalchemy_url


def run_migrations_offline() -> None:
    """Emit the SQL instead of running it (``alembic upgrade head --sql``)."""
    url = database_url()
    context.configure(
        url=url,
        target_metadata=target_metadata,
        literal_binds=True,
        render_as_batch=url.startswith("sqlite"),
        dialect_opts={"paramstyle": "named"},
    )
    with context.begin_transaction():
        context.run_migrations()


def run_migrations_online() -> None:
    """Run the migrations on a live connection, in one transaction."""
    url = database_url()
    engine = migration_engine(url)
    try:
        with engine.connect() as connection:
            context.configure(
                connection=connection,
                target_metadata=target_metadata,
                render_as_batch=url.startswith("sqlite"),
                # pysqlite runs DDL in transactions here (the engine emits BEGIN IMMEDIATE), so
                # a migration killed half-way leaves the database at the previous revision.
                transactional_ddl=True,
                compare_type=True,
            )
            with context.begin_transaction():
                context.run_migrations()
    finally:
        engine.dispose()


if context.is_offline_mode():
    run_migrations_offline()
else:
    run_migrations_online()
