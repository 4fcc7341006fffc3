"""Signed values (HMAC-SHA256) and the service's signing key; no web, database or settings.

:func:`sign` and :func:`verify` make and check ``body.mac`` values with an expiry (session
cookies, view links: :mod:`app.api.session_auth`; view links in webhook payloads:
:mod:`app.jobs.alerts.events`).  :func:`signing_key` is the configured key or the one generated once
into ``<data_dir>/secret-key`` (mode 0600) and shared by every process using that directory.
:func:`webhook_signature` is the ``Scandiff-Signature`` header of a webhook delivery.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import secrets
import time
from functools import lru_cache
from pathlib import Path
from typing import Any

from app.kit.data_layout import DataLayout
from app.kit.files import write_private_file

VIEW_LINK_PURPOSE = "view-link"


class SignatureInvalidError(Exception):
    """A signed value was tampered with, malformed, signed for another purpose or expired."""

    def __init__(self, message: str, *, expired: bool = False) -> None:
        super().__init__(message)
        self.expired = expired


def signing_key(configured: str | None, data_dir: Path) -> bytes:
    """The signing key: ``configured`` when set, else the one generated in ``data_dir``."""
    if configured:
        return configured.encode()
    return data_dir_secret(data_dir)


@lru_cache(maxsize=16)
def data_dir_secret(data_dir: Path) -> bytes:
    """Read ``<data_dir>/secret-key``, creating it (0600, atomically) on first use."""
    path = DataLayout(data_dir).secret_key_file
    if not path.exists():
        write_private_file(path, secrets.token_urlsafe(48) + "\n", overwrite=False)
    key = path.read_text().strip()
    if len(key) < 32:
        raise RuntimeError(f"{path} holds no usable secret key; delete it to make a new one")
    return key.encode()


def _b64encode(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode("ascii")


def _b64decode(text: str) -> bytes:
    return base64.urlsafe_b64decode(text + "=" * (-len(text) % 4))


def _mac(key: bytes, purpose: str, body: str) -> bytes:
    return hmac.new(key, f"{purpose}.{body}".encode(), hashlib.sha256).digest()


def sign(payload: dict[str, Any], purpose: str, key: bytes) -> str:
    """``payload`` (JSON, with an ``exp`` timestamp) signed for ``purpose``: ``body.mac``."""
    body = _b64encode(json.dumps(payload, separators=(",", ":"), sort_keys=True).encode())
    return f"{body}.{_b64encode(_mac(key, purpose, body))}"


def verify(value: str, purpose: str, key: bytes, *, now: float | None = None) -> dict[str, Any]:
    """The payload of a value made by :func:`sign` for ``purpose``.

    Raises
    ------
    SignatureInvalidError
        Bad format or signature (``expired=False``), or past its ``exp`` (``expired=True``).
    """
    body, _, mac = value.partition(".")
    try:
        given = _b64decode(mac)
    except (ValueError, TypeError) as exc:
        raise SignatureInvalidError("malformed signature") from exc
    if not body or not hmac.compare_digest(given, _mac(key, purpose, body)):
        raise SignatureInvalidError("bad signature")
    try:
        payload = json.loads(_b64decode(body))
    except (ValueError, TypeError) as exc:
        raise SignatureInvalidError("malformed payload") from exc
    if not isinstance(payload, dict) or not isinstance(payload.get("exp"), (int, float)):
        raise SignatureInvalidError("payload without expiry")
    if (time.time() if now is None else now) >= payload["exp"]:
        raise SignatureInvalidError("expired", expired=True)
    return payload


def view_link_value(job_id: str, token_id: str, key: bytes, ttl: float) -> tuple[str, float]:
    """A signed view-link value for ``job_id`` naming token ``token_id``, and its expiry."""
    expires_at = float(int(time.time() + ttl))
    value = sign({"job": job_id, "tid": token_id, "exp": expires_at}, VIEW_LINK_PURPOSE, key)
    return value, expires_at


def webhook_signature(secret: str, body: bytes, timestamp: int) -> str:
    """The ``Scandiff-Signature`` header: ``t=<unix seconds>,v1=<hex HMAC-SHA256 of "t.body">``.

    Parameters
    ----------
    secret : str
        The webhook's secret (shown once when the webhook was created).
    body : bytes
        The exact request body sent.
    timestamp : int
        Unix seconds of the attempt.
    """
    mac = hmac.new(secret.encode(), f"{timestamp}.".encode() + body, hashlib.sha256).hexdigest()
    return f"t={timestamp},v1={mac}"
