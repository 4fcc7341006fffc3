"""The one error family of the service layer; the API renders each as ``{"error", "detail"}``.

Services raise these (they know no HTTP framework); :mod:`app.api.errors` maps ``status_code``
to the response and renders ``code`` as ``error`` and the message as ``detail``.  Core input
errors (:class:`app.core.errors.InputError` and subclasses) are mapped there too.
"""

from __future__ import annotations


class AppError(Exception):
    """Base class: an expected failure with an HTTP status, a stable code and a message."""

    status_code: int = 400
    code: str = "bad_request"

    def __init__(
        self, detail: str, *, code: str | None = None, headers: dict[str, str] | None = None
    ) -> None:
        super().__init__(detail)
        self.detail = detail
        self.headers = dict(headers or {})
        if code is not None:
            self.code = code


class BadRequestError(AppError):
    """The request is malformed (400)."""

    status_code = 400
    code = "bad_request"


class AuthenticationError(AppError):
    """No token, or a token that is unknown or revoked (401)."""

    status_code = 401
    code = "unauthorized"


class PermissionDeniedError(AppError):
    """The token's role does not allow this (403)."""

    status_code = 403
    code = "forbidden"


class NotFoundError(AppError):
    """The object does not exist or belongs to another organisation (404)."""

    status_code = 404
    code = "not_found"


class ConflictError(AppError):
    """The request conflicts with the current state (409)."""

    status_code = 409
    code = "conflict"


class PayloadTooLargeError(AppError):
    """The body is larger than the configured cap (413)."""

    status_code = 413
    code = "payload_too_large"


class UnsupportedMediaError(AppError):
    """The content is in no supported format (415)."""

    status_code = 415
    code = "unsupported_media_type"


class ValidationFailedError(AppError):
    """The request is well-formed but its values are not acceptable (422)."""

    status_code = 422
    code = "validation_error"


class TooManyRequestsError(AppError):
    """A per-organisation cap on work in progress is reached; retry later (429)."""

    status_code = 429
    code = "too_many_requests"

    def __init__(self, detail: str, *, retry_after_seconds: int, code: str | None = None) -> None:
        super().__init__(detail, code=code, headers={"Retry-After": str(retry_after_seconds)})
        self.retry_after_seconds = retry_after_seconds


class InsufficientStorageError(AppError):
    """The organisation's storage quota cannot hold this (507)."""

    status_code = 507
    code = "insufficient_storage"
