"""``GET /metrics``: Prometheus text format (public, or behind ``SCANDIFF_METRICS_TOKEN``)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Header
from fastapi.responses import Response

from app.api.deps import SettingsDep
from app.services import metrics as metrics_service

router = APIRouter(tags=["metrics"])


@router.get("/metrics", response_class=Response, include_in_schema=False)
def get_metrics(
    settings: SettingsDep,
    authorization: Annotated[str | None, Header()] = None,
    accept: Annotated[str | None, Header()] = None,
) -> Response:
    """Jobs, queue, durations and uploads of the whole deployment, read from the database."""
    metrics_service.check_scrape_access(settings, authorization)
    body, content_type = metrics_service.render_metrics(settings, accept)
    return Response(body, media_type=content_type)
