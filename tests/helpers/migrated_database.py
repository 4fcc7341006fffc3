"""A fresh database at the newest revision for a test, without running Alembic for each test.

Alembic migrates one SQLite file per test session (:func:`migrated_template`); every test that
needs a fresh database gets a byte copy of it (:func:`install_migrated_database`), which is what
the same migrations would write, for a thousandth of the time.  A database that is not a SQLite
file (the PostgreSQL pass of ``.ci/run``) is migrated by Alembic as before.
"""

from __future__ import annotations

import atexit
import shutil
import sqlite3
import tempfile
from pathlib import Path

from sqlalchemy.engine import make_url

from app.db.migrate import current_revision, head_revision, upgrade_to_head

_templates: dict[str, Path] = {}


def migrated_template() -> Path:
    """A SQLite file migrated by Alembic to head, made once per process (removed at exit).

    Its write-ahead log is folded into the file, so the file alone is the whole database.
    """
    head = head_revision() or "base"
    template = _templates.get(head)
    if template is not None and template.is_file():
        return template
    directory = Path(tempfile.mkdtemp(prefix="scandiff-migrated-"))
    atexit.register(shutil.rmtree, directory, ignore_errors=True)
    template = directory / "scandiff.sqlite3"
    upgrade_to_head(f"sqlite:///{template}")
    connection = sqlite3.connect(template)
    try:
        connection.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    finally:
        connection.close()
    _templates[head] = template
    return template


def install_migrated_database(url: str) -> None:
    """Give ``url`` a fresh database at head: a copy of the template for a new SQLite file,
    Alembic itself otherwise (another database, or a file that already exists)."""
    parsed = make_url(url)
    database = parsed.database if parsed.get_backend_name() == "sqlite" else None
    if not database or database == ":memory:" or Path(database).exists():
        upgrade_to_head(url)
        return
    target = Path(database)
    target.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(migrated_template(), target)
    assert current_revision(url) == head_revision(), f"{target} is not at head after the copy"
