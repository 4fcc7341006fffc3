"""Webhooks of the organisation, their deliveries, and test deliveries."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response

from app.api.deps import PrincipalDep, SessionDep, SettingsDep
from app.services.paging import DEFAULT_LIMIT, MAX_LIMIT
from app.services.schemas import Page
from app.services.webhooks import service as webhooks_service
from app.services.webhooks.schemas import (
    DeliveryPage,
    DeliveryRead,
    WebhookCreate,
    WebhookCreated,
    WebhookRead,
)

router = APIRouter(tags=["webhooks"])

Limit = Annotated[int, Query(ge=1, le=MAX_LIMIT, description="Items per page.")]
Cursor = Annotated[str | None, Query(description="`next_cursor` of the previous page.")]


@router.post("/webhooks", status_code=201, response_model=WebhookCreated)
def create_webhook(
    payload: WebhookCreate, session: SessionDep, settings: SettingsDep, principal: PrincipalDep
) -> WebhookCreated:
    """Create a webhook (admin); the answer shows its secret, this once only."""
    webhook, secret = webhooks_service.create_webhook(session, settings, principal, payload)
    return WebhookCreated(**WebhookRead.from_model(webhook).model_dump(), secret=secret)


@router.get("/webhooks", response_model=Page[WebhookRead])
def list_webhooks(
    session: SessionDep,
    principal: PrincipalDep,
    limit: Limit = DEFAULT_LIMIT,
    cursor: Cursor = None,
) -> Page[WebhookRead]:
    """List the organisation's webhooks, newest first."""
    rows, next_cursor = webhooks_service.list_webhooks(session, principal, limit, cursor)
    items = [WebhookRead.from_model(row) for row in rows]
    return Page[WebhookRead](items=items, next_cursor=next_cursor)


@router.get("/webhooks/{webhook_id}", response_model=WebhookRead)
def get_webhook(webhook_id: str, session: SessionDep, principal: PrincipalDep) -> WebhookRead:
    """Read a webhook (without its secret)."""
    return WebhookRead.from_model(webhooks_service.get_webhook(session, principal, webhook_id))


@router.delete("/webhooks/{webhook_id}", status_code=204, response_class=Response)
def delete_webhook(webhook_id: str, session: SessionDep, principal: PrincipalDep) -> Response:
    """Delete a webhook (admin) and its deliveries."""
    webhooks_service.delete_webhook(session, principal, webhook_id)
    return Response(status_code=204)


@router.get("/webhooks/{webhook_id}/deliveries", response_model=DeliveryPage)
def list_deliveries(
    webhook_id: str,
    session: SessionDep,
    principal: PrincipalDep,
    limit: Limit = DEFAULT_LIMIT,
    cursor: Cursor = None,
) -> DeliveryPage:
    """The webhook's deliveries, newest first: status, attempts, last answer, next attempt."""
    rows, next_cursor = webhooks_service.list_deliveries(
        session, principal, webhook_id, limit, cursor
    )
    return DeliveryPage(
        items=[DeliveryRead.from_model(row) for row in rows], next_cursor=next_cursor
    )


@router.post("/webhooks/{webhook_id}/test", status_code=202, response_model=DeliveryRead)
def send_test(webhook_id: str, session: SessionDep, principal: PrincipalDep) -> DeliveryRead:
    """Queue a test delivery (event ``webhook.test``) to this webhook (admin)."""
    return DeliveryRead.from_model(webhooks_service.send_test(session, principal, webhook_id))
