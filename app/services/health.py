"""Health of the service: can the database be used (and is it migrated), is the queue alive."""

from __future__ import annotations

import logging
from functools import lru_cache
from importlib import metadata
from typing import Any

from sqlalchemy import text

from app.config import Settings
from app.db.migrate import head_revision
from app.db.session import transaction
from app.jobs.queue import queue_health as report_queue_health

logger = logging.getLogger("scandiff.services.health")


@lru_cache(maxsize=1)
def service_version() -> str:
    """The installed package version of scandiff."""
    try:
        return metadata.version("scandiff")
    except metadata.PackageNotFoundError:
        return "0+unknown"


def database_health(settings: Settings) -> dict[str, Any]:
    """``{"status": "ok", "revision": ...}`` or ``{"status": "error", "detail": ...}``."""
    try:
        with transaction(settings.sqlalchemy_url) as session:
            session.execute(text("SELECT 1"))
            revision = session.execute(text("SELECT version_num FROM alembic_version")).scalar()
    except Exception as exc:
        logger.warning("database health check failed: %s", exc)
        return {"status": "error", "detail": f"{type(exc).__name__}: {exc}"}
    head = head_revision()
    if revision != head:
        return {
            "status": "error",
            "detail": f"database at revision {revision}, code expects {head}: run the migrations",
            "revision": revision,
        }
    return {"status": "ok", "revision": revision}


def queue_health(settings: Settings) -> dict[str, Any]:
    """What the job queue reports about itself (``app.jobs.queue.queue_health``)."""
    try:
        return dict(report_queue_health(settings))
    except Exception as exc:
        logger.warning("queue health check failed: %s", exc)
        return {"status": "error", "detail": f"{type(exc).__name__}: {exc}"}


def service_health(settings: Settings) -> tuple[int, dict[str, Any]]:
    """HTTP status (200 while the database works, else 503) and the health report."""
    database = database_health(settings)
    queue = queue_health(settings)
    if database["status"] != "ok":
        status = "unavailable"
    elif queue.get("status", "ok") != "ok":
        status = "degraded"
    else:
        status = "ok"
    body = {"status": status, "version": service_version(), "database": database, "queue": queue}
    return (200 if database["status"] == "ok" else 503), body
