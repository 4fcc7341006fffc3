"""The one error family of the service layer; the API renders each as ``{"error", "detail"}``.

Services raise these (they know no HTTP framework); :mod:`app.api.errors` maps ``status_code``
to the response and renders ``code`` as ``error`` and the message as ``detail``.  Core input
errors (:class:`app.core.errors.InputError` and subclasses) are mapped there too.
"""

from __future__ import annotations

from typing import Any


class AppError(Exception):
    """Base class: an expected failure with an HTTP status, a stable code and a message.

    A subclass names its status and default code on its class line:
    ``class NotFoundError(AppError, status_code=404, code="not_found")``.
    """

    status_code: int = 400
    code: str = "bad_request"

    def __init_subclass__(
        cls, *, status_code: int | None = None, code: str | None = None, **kwargs: Any
    ) -> None:
        super().__init_subclass__(**kwargs)
        if status_code is not None:
            cls.status_code = status_code
        if code is not None:
            cls.code = code

    def __init__(
        self, detail: str, *, code: str | None = None, headers: dict[str, str] | None = None
    ) -> None:
        super().__init__(detail)
        self.detail = detail
        self.headers = dict(headers or {})
        if code is not None:
            self.code = code


class BadRequestError(AppError, status_code=400, code="bad_request"):
    """The request is malformed."""


class AuthenticationError(AppError, status_code=401, code="unauthorized"):
    """No token, or a token that is unknown or revoked."""


class PermissionDeniedError(AppError, status_code=403, code="forbidden"):
    """The token's role does not allow this."""


class NotFoundError(AppError, status_code=404, code="not_found"):
    """The object does not exist or belongs to another organisation."""


class ConflictError(AppError, status_code=409, code="conflict"):
    """The request conflicts with the current state."""


class PayloadTooLargeError(AppError, status_code=413, code="payload_too_large"):
    """The body is larger than the configured cap."""


class UnsupportedMediaError(AppError, status_code=415, code="unsupported_media_type"):
    """The request's content type is not the one the route takes (a tus PATCH body)."""


class ValidationFailedError(AppError, status_code=422, code="validation_error"):
    """The request is well-formed but its values are not acceptable."""


class TooManyRequestsError(AppError, status_code=429, code="too_many_requests"):
    """A per-organisation cap on work in progress is reached; retry later."""

    def __init__(self, detail: str, *, retry_after_seconds: int, code: str | None = None) -> None:
        super().__init__(detail, code=code, headers={"Retry-After": str(retry_after_seconds)})
        self.retry_after_seconds = retry_after_seconds


class InsufficientStorageError(AppError, status_code=507, code="insufficient_storage"):
    """The organisation's storage quota cannot hold this."""


class ServiceUnavailableError(AppError, status_code=503, code="service_unavailable"):
    """Something the request needs (the database) is unavailable now; retry later."""

    def __init__(self, detail: str, *, retry_after_seconds: int, code: str | None = None) -> None:
        super().__init__(detail, code=code, headers={"Retry-After": str(retry_after_seconds)})
        self.retry_after_seconds = retry_after_seconds
