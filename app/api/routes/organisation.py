"""``GET /api/v1/organisation``: the caller's organisation with its usage and quotas."""

from __future__ import annotations

from fastapi import APIRouter

from app.api.deps import PrincipalDep, SessionDep, SettingsDep
from app.services import quotas
from app.services.schemas import OrganisationRead

router = APIRouter(tags=["organisation"])


@router.get("/organisation", response_model=OrganisationRead)
def get_organisation(
    session: SessionDep, settings: SettingsDep, principal: PrincipalDep
) -> OrganisationRead:
    """The caller's organisation: unfinished jobs and stored bytes, with their caps."""
    usage = quotas.organisation_usage(session, settings, principal)
    return OrganisationRead.from_model(usage)
