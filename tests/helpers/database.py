"""Reading a test database: row counts, and rows read outside the service's engine."""

from __future__ import annotations

import sqlite3
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from sqlalchemy import event, func, select

from app.config import Settings
from app.db.session import get_engine, transaction
from tests.helpers.server import ApiServer


def count_rows(api: ApiServer, model: type, **filters: str) -> int:
    """How many rows of ``model`` in ``api``'s database have the column values ``filters``."""
    with transaction(api.settings.sqlalchemy_url) as session:
        statement = select(func.count()).select_from(model)
        for name, value in filters.items():
            statement = statement.where(getattr(model, name) == value)
        return int(session.scalar(statement) or 0)


def database_rows(data_dir: Path, table: str) -> list[dict[str, Any]]:
    """Every row of ``table`` in the SQLite file of a ``scandiff serve`` data directory.

    Read-only and outside the service's engine: in WAL mode a reader never waits for, nor
    blocks, the service's writers.
    """
    connection = sqlite3.connect(f"file:{data_dir / 'scandiff.sqlite3'}?mode=ro", uri=True)
    connection.row_factory = sqlite3.Row
    try:
        return [dict(row) for row in connection.execute(f"SELECT * FROM {table}")]
    finally:
        connection.close()


def job_status_counts(data_dir: Path) -> Counter[str]:
    """How many jobs of a ``scandiff serve`` data directory are in each status."""
    return Counter(job["status"] for job in database_rows(data_dir, "job"))


@contextmanager
def counted_selects(settings: Settings) -> Iterator[list[str]]:
    """The queries (SELECT or WITH) run on the app's engine inside the block."""
    statements: list[str] = []
    engine = get_engine(settings.sqlalchemy_url)

    def note(_conn: Any, _cursor: Any, statement: str, *_args: Any) -> None:
        if statement.lstrip().upper().startswith(("SELECT", "WITH")):
            statements.append(statement)

    event.listen(engine, "before_cursor_execute", note)
    try:
        yield statements
    finally:
        event.remove(engine, "before_cursor_execute", note)
