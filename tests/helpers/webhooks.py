"""A delivery worker for the webhook tests (the receiver itself: :mod:`app.testing.webhooks`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from app.testing.webhooks import WEBHOOK_SETTINGS
from tests.helpers.server import ApiServer
from tests.helpers.worker import WorkerProcess


def environment_of(values: dict[str, Any]) -> dict[str, str]:
    """``SCANDIFF_*`` variables of these settings (for child processes)."""
    return {
        f"SCANDIFF_{name.upper()}": str(value).lower() if isinstance(value, bool) else str(value)
        for name, value in values.items()
    }


def start_delivery_worker(
    worker_factory: Callable[..., WorkerProcess], api: ApiServer, **extra: Any
) -> WorkerProcess:
    """A ``scandiff worker`` (fake pipeline) on ``api``'s data with :data:`WEBHOOK_SETTINGS`,
    ``public_url`` = the API's address, and ``extra`` settings; once its workers run."""
    env = environment_of({**WEBHOOK_SETTINGS, "public_url": api.base_url, **extra})
    worker = worker_factory(api.settings, env=env)
    worker.wait_for_workers()
    return worker
