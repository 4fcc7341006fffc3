"""One way to run a transaction: ``app.db.session.transaction`` commits, then runs the
after-commit callbacks; on error it rolls back and runs the after-rollback ones (real SQLite
file migrated by Alembic)."""

from __future__ import annotations

from pathlib import Path

import pytest
from sqlalchemy import select

from app.config import Settings
from app.db.migrate import upgrade_to_head
from app.db.models import Organisation
from app.db.session import after_commit, after_rollback, transaction


@pytest.fixture
def database_url(tmp_path: Path) -> str:
    url = Settings(data_dir=tmp_path).sqlalchemy_url
    upgrade_to_head(url)
    return url


def organisation_names(url: str) -> list[str]:
    with transaction(url) as session:
        return list(session.scalars(select(Organisation.name)))


def test_after_commit_work_runs_once_the_rows_are_durable(database_url: str) -> None:
    seen: list[list[str]] = []
    with transaction(database_url) as session:
        session.add(Organisation(name="kept"))
        session.flush()
        after_commit(session, lambda: seen.append(organisation_names(database_url)))
        after_rollback(session, lambda: seen.append(["rolled back"]))
        assert seen == []
    assert seen == [["kept"]]  # run after the commit, from another session: the row is there


def test_an_error_rolls_back_and_runs_only_the_clean_ups(database_url: str) -> None:
    seen: list[str] = []
    with pytest.raises(RuntimeError, match="boom"), transaction(database_url) as session:
        session.add(Organisation(name="dropped"))
        session.flush()
        after_commit(session, lambda: seen.append("committed"))
        after_rollback(session, lambda: seen.append("cleaned up"))
        raise RuntimeError("boom")
    assert seen == ["cleaned up"]
    assert organisation_names(database_url) == []


def test_a_failing_callback_is_logged_and_the_others_still_run(
    database_url: str, caplog: pytest.LogCaptureFixture
) -> None:
    seen: list[str] = []

    def failing() -> None:
        raise OSError("disk gone")

    with transaction(database_url) as session:
        after_commit(session, failing)
        after_commit(session, lambda: seen.append("second"))
    assert seen == ["second"]
    assert any("after-commit callback" in record.getMessage() for record in caplog.records)
