"""Helpers for the one transaction owner of a request: after-commit work and read-only ends.

Services ``flush()`` and never commit; they register side effects that must only happen once the
rows are durable (enqueueing a job, deleting files of deleted rows) with :func:`after_commit`,
and clean-ups for when the transaction is abandoned with :func:`after_rollback`.  The owner (the
API's session dependency, a CLI command) calls :func:`commit` or :func:`rollback`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from sqlalchemy.orm import Session

logger = logging.getLogger("scandiff.services")

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


def end_read_transaction(session: Session) -> None:
    """End a transaction that only read, so no lock is held during slow work (uploads, numpy).

    With SQLite every transaction is ``BEGIN IMMEDIATE`` (it takes the write lock), so a request
    that streams a body or parses a cloud must not keep one open meanwhile.
    """
    if session.new or session.dirty or session.deleted:
        raise RuntimeError("end_read_transaction called with pending changes")
    if session.in_transaction():
        session.rollback()
