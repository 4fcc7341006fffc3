"""Opening a SQLite connection waits out a write lock that SQLite will not wait for itself.

Switching a rollback-journal database to WAL while another connection holds its write lock
fails at once with "database is locked", whatever the busy timeout: SQLite skips its busy
handler there. Replicas opening a fresh file together met that window (CI, ten rounds of
``test_replicas_first_start``); every engine made by :mod:`app.db.session` now waits as the
busy handler would.
"""

from __future__ import annotations

import multiprocessing
import sqlite3
import threading
import time
from multiprocessing.synchronize import Barrier as BarrierType
from pathlib import Path

import pytest
from sqlalchemy import text

from app.db.session import DatabaseUnavailableError, _retry_while_locked, make_engine

HOLD_SECONDS = 0.5


def _rollback_journal_database(path: Path) -> sqlite3.Connection:
    """A database in the default rollback-journal mode with one row, and its open connection."""
    connection = sqlite3.connect(path, isolation_level=None, check_same_thread=False)
    connection.execute("CREATE TABLE reading (value INTEGER)")
    connection.execute("INSERT INTO reading VALUES (1)")
    return connection


def test_a_new_connection_waits_for_a_writer_before_switching_to_wal(tmp_path: Path) -> None:
    path = tmp_path / "rollback.sqlite"
    writer = _rollback_journal_database(path)
    writer.execute("BEGIN IMMEDIATE")
    writer.execute("INSERT INTO reading VALUES (2)")
    # Without the wait, the WAL switch below fails at once: SQLite gives up without waiting.
    with pytest.raises(sqlite3.OperationalError, match="database is locked"):
        sqlite3.connect(path, timeout=30).execute("PRAGMA journal_mode = WAL")
    release = threading.Timer(HOLD_SECONDS, lambda: writer.execute("COMMIT"))
    release.start()
    started = time.monotonic()
    engine = make_engine(f"sqlite:///{path}")
    try:
        with engine.connect() as connection:
            mode = connection.exec_driver_sql("PRAGMA journal_mode").scalar()
            rows = connection.execute(text("SELECT count(*) FROM reading")).scalar()
    finally:
        engine.dispose()
        release.join()
        writer.close()
    assert mode == "wal"
    assert rows == 2  # it waited for the writer's commit instead of failing
    assert time.monotonic() - started >= HOLD_SECONDS * 0.5


def test_a_lock_held_past_the_wait_is_reported_as_unavailable(tmp_path: Path) -> None:
    path = tmp_path / "held.sqlite"
    writer = _rollback_journal_database(path)
    writer.execute("BEGIN IMMEDIATE")
    writer.execute("INSERT INTO reading VALUES (2)")
    reader = sqlite3.connect(path, isolation_level=None)
    try:
        with pytest.raises(sqlite3.OperationalError, match="database is locked"):
            _retry_while_locked(
                lambda: reader.execute("PRAGMA journal_mode = WAL"), timeout_seconds=0.2
            )
    finally:
        reader.close()
        writer.execute("ROLLBACK")
        writer.close()


def test_other_errors_are_not_retried(tmp_path: Path) -> None:
    calls: list[int] = []

    def broken() -> None:
        calls.append(1)
        raise sqlite3.OperationalError("no such table: reading")

    with pytest.raises(sqlite3.OperationalError, match="no such table"):
        _retry_while_locked(broken, timeout_seconds=5.0)
    assert len(calls) == 1


def test_unavailable_error_still_names_the_database(tmp_path: Path) -> None:
    directory = tmp_path / "not-a-file"
    directory.mkdir()
    engine = make_engine(f"sqlite:///{directory}")
    with (
        pytest.raises(DatabaseUnavailableError, match="unable to open database file"),
        engine.connect(),
    ):
        pass


PROCESSES = 7
ROUNDS = 150
"""Seven processes (four APIs and three workers at first start) on a fresh file, 150 times:
without the wait, 6 of 400 such rounds lost a process at the WAL switch (``make test-slow``)."""


def _open_and_write(url: str, barrier: BarrierType, table: str) -> None:
    """One process's first start: open an engine, write a row, close (exit 1 on failure)."""
    barrier.wait()
    engine = make_engine(url)
    try:
        with engine.begin() as connection:
            connection.exec_driver_sql(f"CREATE TABLE IF NOT EXISTS {table} (value INTEGER)")
            connection.exec_driver_sql(f"INSERT INTO {table} VALUES (1)")
    except DatabaseUnavailableError:
        raise SystemExit(1) from None
    finally:
        engine.dispose()


@pytest.mark.slow
@pytest.mark.timeout(1200)
def test_processes_opening_a_fresh_file_together_all_connect(tmp_path: Path) -> None:
    context = multiprocessing.get_context("fork")
    failed_rounds = []
    for round_index in range(ROUNDS):
        url = f"sqlite:///{tmp_path / f'fresh-{round_index}.sqlite'}"
        barrier = context.Barrier(PROCESSES)
        processes = [
            context.Process(target=_open_and_write, args=(url, barrier, f"t{index % 3}"))
            for index in range(PROCESSES)
        ]
        for process in processes:
            process.start()
        for process in processes:
            process.join()
        if any(process.exitcode != 0 for process in processes):
            failed_rounds.append(round_index)
    assert failed_rounds == []
