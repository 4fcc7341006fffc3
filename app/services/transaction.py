"""Transactions as services see them: after-commit work, and read-only transactions ended early.

Services ``flush()`` and never commit; they register side effects that must only happen once the
rows are durable (enqueueing a job, deleting files of deleted rows) with :func:`after_commit`,
and clean-ups for when the transaction is abandoned with :func:`after_rollback`.  The owner (the
API's session dependency, or :func:`app.db.session.transaction` anywhere else) calls
:func:`commit` or :func:`rollback`.  Those four live in :mod:`app.db.session` (one
implementation for the API, the jobs and the CLI) and are named here for the services.
"""

from __future__ import annotations

from sqlalchemy.orm import Session

from app.db.session import after_commit, after_rollback, commit, rollback

__all__ = ["after_commit", "after_rollback", "commit", "end_read_transaction", "rollback"]


def end_read_transaction(session: Session) -> None:
    """End a transaction that only read, so no lock is held during slow work (uploads, numpy).

    With SQLite every transaction is ``BEGIN IMMEDIATE`` (it takes the write lock), so a request
    that streams a body or parses a cloud must not keep one open meanwhile.
    """
    if session.new or session.dirty or session.deleted:
        raise RuntimeError("end_read_transaction called with pending changes")
    if session.in_transaction():
        session.rollback()
