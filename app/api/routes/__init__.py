"""Routers of API v1, one per resource; :data:`api_router` gathers them under ``/api/v1``."""

from __future__ import annotations

from fastapi import APIRouter

from app.api.routes import health, jobs, organisation, scans, sites

api_router = APIRouter(prefix="/api/v1")
api_router.include_router(health.router)
api_router.include_router(sites.router)
api_router.include_router(scans.router)
api_router.include_router(jobs.router)
api_router.include_router(organisation.router)
