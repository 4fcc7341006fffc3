"""Tenancy in one place: every read of an organisation's rows is scoped here.

:func:`scoped` adds the organisation filter to a statement: every table in its ``FROM`` that has
an ``organisation_id`` column is filtered, so a selected column or an aggregate is scoped as well
as a whole row.  :func:`get_owned` reads one row by id.  An id that does not exist and an id of
another organisation are the same 404, so a caller learns nothing about other organisations.
"""

from __future__ import annotations

from typing import Any, TypeVar

from sqlalchemy import Select, Table, select
from sqlalchemy.orm import Session

from app.db.models import Job, Scan, Site
from app.services.auth import Principal
from app.services.errors import NotFoundError

SelectT = TypeVar("SelectT", bound=Select[Any])
OwnedT = TypeVar("OwnedT", Site, Scan, Job)


def scoped(statement: SelectT, principal: Principal) -> SelectT:
    """``statement`` limited to the principal's organisation (ValueError when nothing is owned)."""
    owned = [
        from_clause
        for from_clause in statement.get_final_froms()
        if isinstance(from_clause, Table) and "organisation_id" in from_clause.c
    ]
    if not owned:
        raise ValueError(f"no table of this statement belongs to an organisation: {statement}")
    return statement.where(
        *(table.c.organisation_id == principal.organisation_id for table in owned)
    )


def get_owned(session: Session, principal: Principal, model: type[OwnedT], row_id: str) -> OwnedT:
    """The principal's ``model`` row ``row_id``; 404 when it does not exist or is another's."""
    row = session.scalar(scoped(select(model).where(model.id == row_id), principal))
    if row is None:
        raise NotFoundError(f"{model.__tablename__} {row_id} not found")
    return row
