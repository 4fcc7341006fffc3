"""``GET /api/v1/health`` (public)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from app.api.deps import SettingsDep
from app.services import health as health_service
from app.services.schemas import HealthRead

router = APIRouter(tags=["health"])


@router.get("/health", response_model=HealthRead, responses={503: {"model": HealthRead}})
def get_health(settings: SettingsDep) -> JSONResponse:
    """Status of the database and the job queue (200 while the database works, else 503)."""
    status_code, body = health_service.service_health(settings)
    return JSONResponse(body, status_code=status_code)
