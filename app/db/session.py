"""Engine and session factory.

SQLite is tuned for many processes (API + workers) writing at once: WAL journal, a long busy
timeout, and every transaction opened with ``BEGIN IMMEDIATE`` so that a read that later upgrades
to a write can never fail at once with "database is locked" (DESIGN.md measured 5,854 such
errors in 8 s with deferred transactions, 0 with IMMEDIATE).  Keep write transactions short and
never do numeric work inside one.

:func:`transaction` is the one way to run a transaction: it commits with :func:`commit`, which
runs the callbacks registered with :func:`after_commit` (enqueueing a job, deleting the files of
deleted rows) once the rows are durable, or rolls back with :func:`rollback`, which runs the
:func:`after_rollback` clean-ups.

A database that cannot be reached (refused or lost connection; on SQLite a file that stays
locked past the busy timeout or cannot be opened) raises :class:`DatabaseUnavailableError`
instead of the driver's error, from every engine made here: the API answers it with a 503 and
``Retry-After`` (:mod:`app.api.errors`), never a 500.  A dead pooled connection found by the
pool's pre-ping is not such an error: the pool reconnects, so the service recovers by itself.
"""

from __future__ import annotations

import logging
import sqlite3
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from functools import lru_cache

from sqlalchemy import Connection, Engine, create_engine, event
from sqlalchemy.engine import ExceptionContext
from sqlalchemy.exc import InterfaceError, OperationalError
from sqlalchemy.orm import Session, sessionmaker

logger = logging.getLogger("scandiff.db")

SQLITE_BUSY_TIMEOUT_MS = 60_000
SQLITE_LOCKED_RETRY_FIRST_PAUSE_SECONDS = 0.01
SQLITE_LOCKED_RETRY_MAX_PAUSE_SECONDS = 0.5
READ_ONLY_OPTION = "scandiff_read_only"
"""Execution option marking a session that only reads: on SQLite it opens a plain (deferred)
transaction, which in WAL mode never waits for, nor blocks, writers."""


_CHANGES_AT_BEGIN = "scandiff_changes_at_begin"
SQLITE_UNAVAILABLE_MESSAGES = ("database is locked", "unable to open database file")
"""SQLite errors meaning "the database cannot be used now", not "this statement is wrong"."""


class DatabaseUnavailableError(Exception):
    """The database cannot be reached now (connection refused or lost, file locked or gone).

    Raised instead of the driver's error (kept as ``__cause__``); retrying later may succeed.
    """


def unavailable_error(context: ExceptionContext) -> DatabaseUnavailableError | None:
    """The :class:`DatabaseUnavailableError` standing for this engine error, if it is one."""
    error = context.sqlalchemy_exception
    if context.is_pre_ping or not isinstance(error, (OperationalError, InterfaceError)):
        return None
    original = str(context.original_exception).strip()
    if context.dialect is not None and context.dialect.name == "sqlite":
        if not original.startswith(SQLITE_UNAVAILABLE_MESSAGES):
            return None
    elif not (context.is_disconnect or context.connection is None):
        return None  # a statement the server refused (say a deadlock): not an outage
    reason = original.splitlines()[0] if original else type(context.original_exception).__name__
    unavailable = DatabaseUnavailableError(f"the database is unavailable: {reason}")
    unavailable.__cause__ = error
    return unavailable


def _report_unavailable_databases(engine: Engine) -> None:
    """Make ``engine`` raise :class:`DatabaseUnavailableError` for an unreachable database."""

    @event.listens_for(engine, "handle_error")
    def _on_error(context: ExceptionContext) -> DatabaseUnavailableError | None:
        return unavailable_error(context)


def _total_changes(connection: Connection) -> int | None:
    """Rows changed on this DBAPI connection since it opened (sqlite3), else None."""
    return getattr(connection.connection.dbapi_connection, "total_changes", None)


def read_transaction_wrote(session: Session) -> bool:
    """Whether the open transaction of a read-only session changed rows (True if unsure).

    False means ending it is free of I/O and lock waits (a deferred SQLite transaction that
    only read), so the API may commit it without a worker-thread hop.
    """
    if not session.in_transaction():
        return False
    connection = session.connection()
    at_begin = connection.info.get(_CHANGES_AT_BEGIN)
    return at_begin is None or _total_changes(connection) != at_begin


def _execute_all(dbapi_connection, statements: tuple[str, ...]) -> None:  # type: ignore[no-untyped-def]
    """Run ``statements`` on a raw DBAPI connection, in order."""
    cursor = dbapi_connection.cursor()
    try:
        for statement in statements:
            cursor.execute(statement)
    finally:
        cursor.close()


def _retry_while_locked(
    action: Callable[[], None], *, timeout_seconds: float = SQLITE_BUSY_TIMEOUT_MS / 1000
) -> None:
    """Run ``action``, again while SQLite answers "database is locked", for ``timeout_seconds``.

    SQLite skips its busy handler where waiting could deadlock: switching a rollback-journal
    database to WAL while another connection holds its write lock fails at once, whatever the
    busy timeout.  Seven processes opening a fresh file together can meet that window (one
    replica in ten rounds of ``tests/db/test_replicas_first_start.py`` died of it), so the
    connection's set-up waits here, with backoff, as the busy handler would.
    """
    deadline = time.monotonic() + timeout_seconds
    pause = SQLITE_LOCKED_RETRY_FIRST_PAUSE_SECONDS
    while True:
        try:
            action()
            return
        except sqlite3.OperationalError as exc:
            if not str(exc).startswith("database is locked") or time.monotonic() >= deadline:
                raise
        time.sleep(min(pause, max(0.0, deadline - time.monotonic())))
        pause = min(2 * pause, SQLITE_LOCKED_RETRY_MAX_PAUSE_SECONDS)


def _configure_sqlite(engine: Engine, *, foreign_keys: bool = True) -> None:
    """WAL, busy timeout, foreign keys and BEGIN IMMEDIATE on every SQLite connection."""

    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_connection, _record) -> None:  # type: ignore[no-untyped-def]
        # Let SQLAlchemy, not the sqlite3 module, emit BEGIN (pysqlite's own is deferred).
        dbapi_connection.isolation_level = None
        pragmas = (
            f"PRAGMA busy_timeout = {SQLITE_BUSY_TIMEOUT_MS}",
            "PRAGMA journal_mode = WAL",
            "PRAGMA synchronous = NORMAL",
            f"PRAGMA foreign_keys = {'ON' if foreign_keys else 'OFF'}",
        )
        _retry_while_locked(lambda: _execute_all(dbapi_connection, pragmas))

    @event.listens_for(engine, "begin")
    def _on_begin(connection) -> None:  # type: ignore[no-untyped-def]
        if connection.get_execution_options().get(READ_ONLY_OPTION):
            connection.exec_driver_sql("BEGIN")
            connection.info[_CHANGES_AT_BEGIN] = _total_changes(connection)
        else:
            connection.exec_driver_sql("BEGIN IMMEDIATE")


def make_engine(url: str, *, foreign_keys: bool = True) -> Engine:
    """An engine for ``url`` with the SQLite tuning above when it is SQLite.

    ``foreign_keys=False`` is for migrations: batch migrations recreate tables, and dropping a
    parent table with foreign keys on would cascade-delete its children's rows.
    """
    if url.startswith("sqlite"):
        engine = create_engine(
            url,
            connect_args={"timeout": SQLITE_BUSY_TIMEOUT_MS / 1000, "check_same_thread": False},
            # More connections than the API admits requests (app.api.concurrency), so an
            # admitted request never waits for one.
            pool_size=10,
            max_overflow=30,
        )
        _configure_sqlite(engine, foreign_keys=foreign_keys)
    else:
        engine = create_engine(url, pool_pre_ping=True)
    _report_unavailable_databases(engine)
    return engine


@lru_cache(maxsize=8)
def get_engine(url: str) -> Engine:
    """One engine per URL per process."""
    return make_engine(url)


def session_factory(url: str, *, read_only: bool = False) -> sessionmaker[Session]:
    """A sessionmaker bound to the engine for ``url``.

    ``read_only=True`` is for requests that never write (GET): on SQLite their transactions are
    deferred, so a hundred concurrent status polls do not queue behind each other and behind
    the workers for the write lock (``BEGIN IMMEDIATE``), which is what writers need.
    """
    return _sessionmaker_for(get_engine(url), read_only)


@lru_cache(maxsize=16)
def _sessionmaker_for(engine: Engine, read_only: bool) -> sessionmaker[Session]:
    """One sessionmaker per engine and mode (an option engine and a sessionmaker cost ~0.1 ms
    to build, which a status poll paid every request)."""
    if read_only:
        engine = engine.execution_options(**{READ_ONLY_OPTION: True})
    return sessionmaker(bind=engine, expire_on_commit=False)


_AFTER_COMMIT = "scandiff_after_commit"
_AFTER_ROLLBACK = "scandiff_after_rollback"


def after_commit(session: Session, callback: Callable[[], None]) -> None:
    """Run ``callback`` once the session's transaction has committed (errors are logged)."""
    session.info.setdefault(_AFTER_COMMIT, []).append(callback)


def after_rollback(session: Session, callback: Callable[[], None]) -> None:
    """Run ``callback`` if the session's transaction is rolled back instead of committed."""
    session.info.setdefault(_AFTER_ROLLBACK, []).append(callback)


def _run(callbacks: list[Callable[[], None]], what: str) -> None:
    for callback in callbacks:
        try:
            callback()
        except Exception:
            logger.exception("%s callback %r failed", what, callback)


def commit(session: Session) -> None:
    """Commit, then run the after-commit callbacks; roll back (and clean up) if commit fails."""
    try:
        session.commit()
    except BaseException:
        rollback(session)
        raise
    session.info.pop(_AFTER_ROLLBACK, None)
    _run(session.info.pop(_AFTER_COMMIT, []), "after-commit")


def rollback(session: Session) -> None:
    """Roll back, drop the after-commit callbacks and run the after-rollback ones."""
    try:
        session.rollback()
    finally:
        session.info.pop(_AFTER_COMMIT, None)
        _run(session.info.pop(_AFTER_ROLLBACK, []), "after-rollback")


@contextmanager
def transaction(url: str) -> Iterator[Session]:
    """A session committed on success, then its after-commit callbacks run; rolled back (and
    its after-rollback callbacks run) on error.  The one way to run a transaction outside a
    request (the API's request session ends with the same :func:`commit` / :func:`rollback`)."""
    session = session_factory(url)()
    try:
        yield session
        commit(session)
    except BaseException:
        rollback(session)
        raise
    finally:
        session.close()
