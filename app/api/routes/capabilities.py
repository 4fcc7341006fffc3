"""What this server reads and runs (upload formats, detectors)."""

from __future__ import annotations

from fastapi import APIRouter

from app.api.deps import PrincipalDep
from app.services import capabilities as capabilities_service
from app.services.schemas import CapabilitiesRead

router = APIRouter(tags=["capabilities"])


@router.get("/capabilities", response_model=CapabilitiesRead)
def get_capabilities(principal: PrincipalDep) -> CapabilitiesRead:
    """The upload formats read and the detector methods and variants run."""
    return capabilities_service.capabilities()
