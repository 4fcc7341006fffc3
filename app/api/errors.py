"""One JSON shape for every error: ``{"error": <code>, "detail": <message>}`` with its status.

Service errors (:class:`app.services.errors.AppError`) carry their status and code; core input
errors map to 415 (unsupported format), 400 (malformed point cloud) or 422 (other bad input);
request validation is 422; unknown routes and methods keep their status; an unreachable
database (:class:`app.db.session.DatabaseUnavailableError`, wherever it is raised) is a 503
``database_unavailable`` with ``Retry-After``; anything else is a 500 whose detail names the
request id to look up in the logs.
"""

from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

from app.core.errors import (
    InputError,
    PointCloudError,
    PointLimitError,
    UnsupportedFormatError,
)
from app.db.session import DatabaseUnavailableError
from app.services.errors import AppError, ServiceUnavailableError
from app.services.messages import api_limit_message
from app.services.schemas import ErrorRead

logger = logging.getLogger("scandiff.api")

_HTTP_CODES = {
    400: "bad_request",
    401: "unauthorized",
    403: "forbidden",
    404: "not_found",
    405: "method_not_allowed",
    406: "not_acceptable",
    409: "conflict",
    413: "payload_too_large",
    415: "unsupported_media_type",
    422: "validation_error",
    429: "too_many_requests",
    503: "service_unavailable",
    507: "insufficient_storage",
}


DATABASE_RETRY_AFTER_SECONDS = 5
"""``Retry-After`` of the 503 sent while the database is unreachable."""

QUEUED_JOBS_RESPONSE: dict[str, Any] = {
    "model": ErrorRead,
    "description": "The organisation has its cap of unfinished jobs "
    "(SCANDIFF_MAX_QUEUED_JOBS_PER_ORGANISATION); nothing was stored. Retry after the "
    "`Retry-After` seconds.",
    "headers": {
        "Retry-After": {
            "description": "Seconds to wait before retrying.",
            "schema": {"type": "integer"},
        }
    },
}
"""OpenAPI entry of the 429 of operations that create a job."""

STORAGE_QUOTA_RESPONSE: dict[str, Any] = {
    "model": ErrorRead,
    "description": "The upload would pass the organisation's storage quota "
    "(SCANDIFF_MAX_STORED_BYTES_PER_ORGANISATION); nothing was stored.",
}
"""OpenAPI entry of the 507 of uploads."""


def error_response(
    status_code: int, code: str, detail: str, headers: dict[str, str] | None = None
) -> JSONResponse:
    """The JSON error response."""
    return JSONResponse({"error": code, "detail": detail}, status_code=status_code, headers=headers)


def request_id_of(request: Request) -> str | None:
    """The id the logging middleware gave this request."""
    return request.scope.get("state", {}).get("request_id")


async def handle_app_error(request: Request, exc: Exception) -> JSONResponse:
    """Render a service error with its own status and code."""
    assert isinstance(exc, AppError)
    headers = dict(exc.headers)
    if exc.status_code == 401:
        headers["WWW-Authenticate"] = "Bearer"
    return error_response(exc.status_code, exc.code, exc.detail, headers or None)


async def handle_input_error(request: Request, exc: Exception) -> JSONResponse:
    """Render a core input error: 415 unknown format, 400 malformed cloud, 422 other input."""
    if isinstance(exc, UnsupportedFormatError):
        return error_response(415, "unsupported_format", str(exc))
    if isinstance(exc, PointLimitError):
        return error_response(
            400, "malformed_point_cloud", api_limit_message(str(exc), exc.limit_name)
        )
    if isinstance(exc, PointCloudError):
        return error_response(400, "malformed_point_cloud", str(exc))
    return error_response(422, "invalid_input", str(exc))


def _location(error: dict[str, Any]) -> str:
    return ".".join(str(part) for part in error.get("loc", ()))


async def handle_validation_error(request: Request, exc: Exception) -> JSONResponse:
    """Render request validation problems as one readable 422 message."""
    assert isinstance(exc, RequestValidationError)
    messages = [
        f"{_location(error)}: {error.get('msg', 'invalid')}" if _location(error) else error["msg"]
        for error in exc.errors()
    ]
    return error_response(422, "validation_error", "; ".join(messages) or "invalid request")


async def handle_http_exception(request: Request, exc: Exception) -> JSONResponse:
    """Render framework HTTP errors (unknown route, wrong method...) in the same shape."""
    assert isinstance(exc, StarletteHTTPException)
    code = _HTTP_CODES.get(exc.status_code, "error")
    return error_response(exc.status_code, code, str(exc.detail), dict(exc.headers or {}) or None)


async def handle_client_disconnect(request: Request, exc: Exception) -> JSONResponse:
    """The client went away mid-request (nobody reads this answer)."""
    return error_response(400, "client_disconnected", "the client disconnected mid-request")


def database_unavailable(exc: DatabaseUnavailableError) -> ServiceUnavailableError:
    """The 503 answering a request that needed an unreachable database."""
    return ServiceUnavailableError(
        f"{exc}. Nothing was stored; retry after {DATABASE_RETRY_AFTER_SECONDS} seconds.",
        retry_after_seconds=DATABASE_RETRY_AFTER_SECONDS,
        code="database_unavailable",
    )


def unavailable_database_in(exc: BaseException) -> DatabaseUnavailableError | None:
    """The :class:`DatabaseUnavailableError` in ``exc``, its causes or its group, if any."""
    seen: set[int] = set()
    pending: list[BaseException] = [exc]
    while pending:
        current = pending.pop()
        if id(current) in seen:
            continue
        seen.add(id(current))
        if isinstance(current, DatabaseUnavailableError):
            return current
        if isinstance(current, BaseExceptionGroup):
            pending.extend(current.exceptions)
        pending.extend(link for link in (current.__cause__, current.__context__) if link)
    return None


async def handle_database_unavailable(request: Request, exc: Exception) -> JSONResponse:
    """Render an unreachable database as a 503 with ``Retry-After`` (logged, one line)."""
    assert isinstance(exc, DatabaseUnavailableError)
    logger.warning("database unavailable (request id %s): %s", request_id_of(request), exc)
    return await handle_app_error(request, database_unavailable(exc))


async def handle_unexpected_error(request: Request, exc: Exception) -> JSONResponse:
    """Log the bug with the request id and answer a 500 without internals.

    An unreachable database raised outside a route (a middleware, a dependency's teardown,
    wrapped in another error or a group) is still the 503 of :func:`handle_database_unavailable`.
    """
    unavailable = unavailable_database_in(exc)
    if unavailable is not None:
        return await handle_database_unavailable(request, unavailable)
    request_id = request_id_of(request)
    logger.exception("unhandled error (request id %s)", request_id)
    return error_response(
        500, "internal_error", f"internal server error; request id {request_id or 'unknown'}"
    )


def install_error_handlers(app: FastAPI) -> None:
    """Register every handler above on ``app``."""
    app.add_exception_handler(AppError, handle_app_error)
    app.add_exception_handler(DatabaseUnavailableError, handle_database_unavailable)
    app.add_exception_handler(InputError, handle_input_error)
    app.add_exception_handler(RequestValidationError, handle_validation_error)
    app.add_exception_handler(StarletteHTTPException, handle_http_exception)
    app.add_exception_handler(ClientDisconnect, handle_client_disconnect)
    app.add_exception_handler(Exception, handle_unexpected_error)


def document_error_shape(app: FastAPI) -> None:
    """Make ``/openapi.json`` describe the 422 the handlers send (``ErrorRead``).

    FastAPI documents every 422 as its own ``HTTPValidationError`` (``detail`` a list), a shape
    this app never sends; clients generated from the document (and schemathesis) then reject
    every real validation error.
    """
    generate = app.openapi

    def openapi() -> dict[str, Any]:
        schema = generate()
        components = schema.setdefault("components", {}).setdefault("schemas", {})
        if "ErrorRead" not in components:
            components["ErrorRead"] = ErrorRead.model_json_schema()
        error_content = {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorRead"}}}
        for operations in schema.get("paths", {}).values():
            for operation in operations.values():
                response = operation.get("responses", {}).get("422")
                if response is not None:
                    response["description"] = "Validation error"
                    response["content"] = error_content
        components.pop("HTTPValidationError", None)
        components.pop("ValidationError", None)
        return schema

    app.openapi = openapi  # type: ignore[method-assign]
