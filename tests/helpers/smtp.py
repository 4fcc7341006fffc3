"""A real local SMTP server (aiosmtpd) for the e-mail alert tests.

:class:`SmtpServer` listens on 127.0.0.1 (a thread of its own), keeps every message it
accepted, and answers ``451`` (try again later) to the first ``fail_first`` messages.
"""

from __future__ import annotations

import email
import email.policy
from email.message import EmailMessage
from typing import Any

from aiosmtpd.controller import Controller

from app.testing.network import free_port
from app.testing.waiting import wait_until


class SmtpServer:
    """aiosmtpd on a free port: ``messages`` accepted, ``refused`` how many were answered 451."""

    def __init__(self, *, fail_first: int = 0) -> None:
        self.fail_first = fail_first
        self.refused = 0
        self.messages: list[EmailMessage] = []
        self.recipients: list[list[str]] = []
        self.port = free_port()
        self.controller = Controller(self, hostname="127.0.0.1", port=self.port)

    async def handle_DATA(self, server: Any, session: Any, envelope: Any) -> str:  # noqa: N802
        """aiosmtpd's hook: refuse the first ``fail_first`` messages, then keep them."""
        if self.refused < self.fail_first:
            self.refused += 1
            return "451 4.3.0 try again later (on purpose)"
        message = email.message_from_bytes(envelope.content, policy=email.policy.default)
        self.messages.append(message)  # type: ignore[arg-type]
        self.recipients.append(list(envelope.rcpt_tos))
        return "250 OK"

    def wait_for_messages(self, count: int = 1, timeout: float = 60.0) -> list[EmailMessage]:
        """Wait until ``count`` messages were accepted; all of them."""
        wait_until(lambda: len(self.messages) >= count, timeout, f"{count} e-mails accepted")
        return list(self.messages)

    def __enter__(self) -> SmtpServer:
        self.controller.start()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.controller.stop()
