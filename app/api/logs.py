"""Structured logs: one JSON line per request (method, path, status, duration, request id).

Headers are never logged (the bearer token lives there), nor query strings.  The request id
comes from a well-formed ``X-Request-ID`` header or is generated, and is echoed in the response.
It is bound for the whole request (:func:`app.log.bind_request_id`): every line logged while
serving it carries it, and a job the request creates stores it (``job.request_id``).
"""

from __future__ import annotations

import logging
import re
import time
import uuid

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.log import JsonFormatter, bind_request_id, make_handler

__all__ = ["JsonFormatter", "RequestLogMiddleware", "configure_logging"]

access_logger = logging.getLogger("scandiff.api.access")

REQUEST_ID_HEADER = "x-request-id"
_VALID_REQUEST_ID = re.compile(r"^[A-Za-z0-9._-]{1,64}$")
UVICORN_LOGGERS = ("uvicorn", "uvicorn.error", "uvicorn.access")
"""Uvicorn's loggers (server start, protocol errors, its access log), sent to the same handler
so that every line of an API process has the same shape."""


def configure_logging(level: str = "INFO", log_format: str | None = None) -> None:
    """Send ``scandiff.*`` and uvicorn's logs to stderr as JSON (or text) lines, unless logging
    is already configured (``log_format`` None: ``SCANDIFF_LOG_FORMAT``)."""
    scandiff_logger = logging.getLogger("scandiff")
    scandiff_logger.setLevel(level.upper())
    if logging.getLogger().handlers or scandiff_logger.handlers:
        return
    handler = make_handler(log_format)
    scandiff_logger.addHandler(handler)
    for name in UVICORN_LOGGERS:
        uvicorn_logger = logging.getLogger(name)
        for existing in list(uvicorn_logger.handlers):
            uvicorn_logger.removeHandler(existing)
        uvicorn_logger.addHandler(handler)
        uvicorn_logger.propagate = False


class RequestLogMiddleware:
    """Pure ASGI middleware (streams untouched) logging each HTTP request once it finished."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        supplied = (
            dict(scope.get("headers") or []).get(REQUEST_ID_HEADER.encode(), b"").decode("latin-1")
        )
        request_id = supplied if _VALID_REQUEST_ID.match(supplied) else uuid.uuid4().hex
        scope.setdefault("state", {})["request_id"] = request_id
        status_code = 500
        started = time.perf_counter()

        async def send_with_request_id(message: Message) -> None:
            nonlocal status_code
            if message["type"] == "http.response.start":
                status_code = message["status"]
                headers = list(message.get("headers") or [])
                headers.append((REQUEST_ID_HEADER.encode(), request_id.encode()))
                message = {**message, "headers": headers}
            await send(message)

        try:
            with bind_request_id(request_id):
                await self.app(scope, receive, send_with_request_id)
        finally:
            duration_ms = (time.perf_counter() - started) * 1000.0
            access_logger.info(
                "%s %s %d",
                scope.get("method"),
                scope.get("path"),
                status_code,
                extra={
                    "event": "request",
                    "method": scope.get("method"),
                    "path": scope.get("path"),
                    "status": status_code,
                    "duration_ms": round(duration_ms, 2),
                    "request_id": request_id,
                },
            )
