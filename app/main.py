"""The FastAPI application: ``create_app(settings)``; ``uvicorn --factory app.main:create_app``.

API v1 lives under ``/api/v1`` (see ``docs/api.md``), OpenAPI at ``/openapi.json``, browsable
at ``/docs`` (Swagger UI) and ``/redoc`` (ReDoc), both served from the assets the
``fastapi-offline`` package ships (:mod:`app.api.docs`): no request leaves the machine.  The app
does not migrate the database: ``scandiff serve`` applies the
migrations and sweeps leftovers before starting it.
"""

from __future__ import annotations

import logging

from fastapi import FastAPI

from app.api.browser import include_browser_routes
from app.api.concurrency import ConcurrencyLimitMiddleware
from app.api.docs import install_offline_docs
from app.api.errors import document_error_shape, install_error_handlers
from app.api.logs import RequestLogMiddleware, configure_logging
from app.api.routes import api_router
from app.config import Settings, get_settings
from app.services import auth, storage
from app.services.health import service_version

logger = logging.getLogger("scandiff.api")

DESCRIPTION = (
    "Detects and locates changes between 3D scans of a site. Authenticate with "
    "`Authorization: Bearer <token>` (`scandiff token create`). Every error is "
    '`{"error": <code>, "detail": <message>}`.'
)


def create_app(settings: Settings | None = None) -> FastAPI:
    """The application for ``settings`` (default: from ``SCANDIFF_*`` environment variables)."""
    settings = settings or get_settings()
    configure_logging(settings.log_level, settings.log_format)
    storage.ensure_directories(settings)
    auth.configure_token_cache(settings.token_cache_seconds)
    app = FastAPI(
        title="scandiff",
        version=service_version(),
        description=DESCRIPTION,
        docs_url=None,  # install_offline_docs: /docs and /redoc without a CDN
        redoc_url=None,
        openapi_url="/openapi.json",
    )
    install_offline_docs(app)
    app.state.settings = settings
    install_error_handlers(app)
    app.add_middleware(
        ConcurrencyLimitMiddleware,
        max_reads=settings.max_concurrent_reads,
        max_writes=settings.max_concurrent_writes,
    )
    app.add_middleware(RequestLogMiddleware)
    app.include_router(api_router)
    include_browser_routes(app, settings)
    document_error_shape(app)
    return app
