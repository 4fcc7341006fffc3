"""The organisation scope (app.services.scoping): rows, columns and aggregates are filtered, an
unowned statement is refused, and another organisation's id is the same 404 as an unknown one."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from sqlalchemy import create_engine, func, select
from sqlalchemy.orm import Session

from app.db.models import Base, Organisation, Region, Site
from app.services.auth import Principal
from app.services.errors import NotFoundError
from app.services.scoping import get_owned, scoped


@pytest.fixture
def session() -> Iterator[Session]:
    """An in-memory database with two organisations, each with one site."""
    engine = create_engine("sqlite://")
    Base.metadata.create_all(engine)
    with Session(engine) as session:
        for name in ("ours", "theirs"):
            organisation = Organisation(id=f"{name}-org", name=name)
            session.add(organisation)
            session.add(Site(id=f"{name}-site", organisation_id=organisation.id, name="site"))
        session.flush()
        yield session
    engine.dispose()


def principal_of(organisation_id: str) -> Principal:
    return Principal(organisation_id=organisation_id, role="reader", token_id="token")


def test_rows_columns_and_aggregates_are_scoped(session: Session) -> None:
    ours = principal_of("ours-org")
    assert [site.id for site in session.scalars(scoped(select(Site), ours))] == ["ours-site"]
    assert session.scalars(scoped(select(Site.name), ours)).all() == ["site"]
    assert session.scalar(scoped(select(func.count()).select_from(Site), ours)) == 1
    assert session.scalar(scoped(select(func.count(Site.id)), principal_of("nobody"))) == 0


def test_a_statement_without_an_owned_table_is_refused(session: Session) -> None:
    with pytest.raises(ValueError, match="belongs to an organisation"):
        scoped(select(Region), principal_of("ours-org"))


def test_another_organisations_id_is_the_same_404_as_an_unknown_one(session: Session) -> None:
    ours = principal_of("ours-org")
    assert get_owned(session, ours, Site, "ours-site").id == "ours-site"
    with pytest.raises(NotFoundError) as another:
        get_owned(session, ours, Site, "theirs-site")
    with pytest.raises(NotFoundError) as unknown:
        get_owned(session, ours, Site, "no-such-site")
    assert str(another.value) == "site theirs-site not found"
    assert str(unknown.value) == "site no-such-site not found"
    assert (another.value.status_code, another.value.code) == (404, "not_found")
