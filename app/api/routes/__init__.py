"""Routers: API v1, one per resource, under ``/api/v1``; ``/metrics`` for Prometheus at the root.

:data:`api_router` gathers them all (the app includes it once).
"""

from __future__ import annotations

from fastapi import APIRouter

from app.api.routes import (
    capabilities,
    health,
    jobs,
    metrics,
    organisation,
    resumable_uploads,
    scans,
    schedules,
    sites,
    verdicts,
    webhooks,
)

v1_router = APIRouter(prefix="/api/v1")
v1_router.include_router(health.router)
v1_router.include_router(sites.router)
v1_router.include_router(scans.router)
v1_router.include_router(resumable_uploads.router)
v1_router.include_router(jobs.router)
v1_router.include_router(verdicts.router)
v1_router.include_router(organisation.router)
v1_router.include_router(capabilities.router)
v1_router.include_router(schedules.router)
v1_router.include_router(webhooks.router)

api_router = APIRouter()
api_router.include_router(v1_router)
api_router.include_router(metrics.router)
