"""A real local webhook receiver (tests, benchmarks), and the docs' signature check.

:class:`WebhookReceiver` is an HTTP server on 127.0.0.1 (a thread) that records every request
with its headers and raw body, and checks its ``Scandiff-Signature`` with the very function
``docs/webhooks.md`` shows (:func:`docs_verifier`, the Python block of that page, executed).
A request whose signature does not check is answered 401.  It can answer 500 to the first
``fail_first`` requests, and hold the first ``hold_first`` requests without answering until
:meth:`release` (a delivery caught in flight), or redirect every request (``redirect_to``).
"""

from __future__ import annotations

import json
import re
import threading
from collections.abc import Callable
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

from sqlalchemy.orm import Session

from app.db.models import Organisation, Webhook
from app.testing.paths import PROJECT_ROOT
from app.testing.waiting import wait_until

WEBHOOK_SETTINGS: dict[str, Any] = {
    "allow_private_addresses": True,  # receivers are on 127.0.0.1
    "webhook_backoff_seconds": 0.2,
    "webhook_backoff_max_seconds": 1.0,
    "webhook_timeout_seconds": 5.0,
    "webhook_lease_seconds": 30.0,
    "webhook_poll_seconds": 0.2,
    "webhook_max_attempts": 5,
}
"""Fast retries, local receivers allowed: the settings of the delivery tests."""

DOCS_PAGE = PROJECT_ROOT / "docs" / "webhooks.md"
DOCS_FUNCTION = "verify_scandiff_signature"


def docs_verification_snippet() -> str:
    """The Python code block of ``docs/webhooks.md`` that defines the signature check."""
    blocks = re.findall(r"```python\n(.*?)```", DOCS_PAGE.read_text(), flags=re.DOTALL)
    matching = [block for block in blocks if f"def {DOCS_FUNCTION}(" in block]
    assert len(matching) == 1, f"{DOCS_PAGE} must hold one python block defining {DOCS_FUNCTION}"
    return matching[0]


def docs_verifier() -> Callable[..., bool]:
    """``verify_scandiff_signature(secret, header, body, tolerance=300)`` as the docs define it."""
    namespace: dict[str, Any] = {}
    exec(compile(docs_verification_snippet(), str(DOCS_PAGE), "exec"), namespace)
    return namespace[DOCS_FUNCTION]


@dataclass(frozen=True)
class ReceivedDelivery:
    """One request the receiver got: headers (lower-case names), raw body, what it answered."""

    headers: dict[str, str]
    body: bytes
    signature_valid: bool
    answered: int | None

    @property
    def event_id(self) -> str:
        """The ``Scandiff-Event-Id`` header."""
        return self.headers.get("scandiff-event-id", "")

    def json(self) -> dict[str, Any]:
        """The body as JSON."""
        return json.loads(self.body)


class WebhookReceiver:
    """A local HTTP receiver that checks signatures, fails or holds requests on purpose."""

    def __init__(
        self, *, fail_first: int = 0, hold_first: int = 0, redirect_to: str | None = None
    ) -> None:
        self.secret = ""
        self.redirect_to = redirect_to
        self.fail_first = fail_first
        self.hold_first = hold_first
        self.received: list[ReceivedDelivery] = []
        self.held = threading.Event()
        self._release = threading.Event()
        self._lock = threading.Lock()
        self._requests = 0
        self._verify = docs_verifier()
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:
                body = self.rfile.read(int(self.headers.get("Content-Length") or 0))
                headers = {name.lower(): value for name, value in self.headers.items()}
                receiver.handle(self, headers, body)

            def log_message(self, *args: Any) -> None:
                return

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.server.daemon_threads = True
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)

    @property
    def url(self) -> str:
        """Where to send deliveries."""
        return f"http://127.0.0.1:{self.server.server_address[1]}/hooks/scandiff"

    def handle(self, handler: BaseHTTPRequestHandler, headers: dict[str, str], body: bytes) -> None:
        """Record the request; hold it, fail it or accept it."""
        valid = bool(self.secret) and self._verify(
            self.secret, headers.get("scandiff-signature", ""), body
        )
        with self._lock:
            self._requests += 1
            number = self._requests
        if number <= self.hold_first:
            self.received.append(ReceivedDelivery(headers, body, valid, None))
            self.held.set()
            self._release.wait(120)
            return  # no answer: the sender is gone by now (or gives up at its timeout)
        status = 500 if number <= self.hold_first + self.fail_first else 200
        status = status if valid else 401
        status = 307 if self.redirect_to else status
        self.received.append(ReceivedDelivery(headers, body, valid, status))
        answer = b'{"ok": true}' if status == 200 else b'{"error": "on purpose"}'
        handler.send_response(status)
        if self.redirect_to:
            handler.send_header("Location", self.redirect_to)
        handler.send_header("Content-Type", "application/json")
        handler.send_header("Content-Length", str(len(answer)))
        handler.end_headers()
        handler.wfile.write(answer)

    def accepted(self) -> list[ReceivedDelivery]:
        """The requests answered 200."""
        return [delivery for delivery in self.received if delivery.answered == 200]

    def wait_for_accepted(self, count: int = 1, timeout: float = 60.0) -> list[ReceivedDelivery]:
        """Wait until ``count`` requests were answered 200; all requests received."""
        wait_until(lambda: len(self.accepted()) >= count, timeout, f"{count} accepted deliveries")
        return list(self.received)

    def release(self) -> None:
        """Let held requests go."""
        self._release.set()

    def __enter__(self) -> WebhookReceiver:
        self.thread.start()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.release()
        self.server.shutdown()
        self.server.server_close()


def organisation_with_webhook(
    session: Session, name: str, url: str, secret: str, events: list[str]
) -> str:
    """A new organisation ``name`` with one webhook to ``url`` for ``events``; its id."""
    organisation = Organisation(name=name)
    session.add(organisation)
    session.flush()
    session.add(Webhook(organisation_id=organisation.id, url=url, events=events, secret=secret))
    session.flush()
    return organisation.id
