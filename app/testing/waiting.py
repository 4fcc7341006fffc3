"""Polling: wait until a condition holds."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TypeVar

Value = TypeVar("Value")


def wait_until(
    condition: Callable[[], Value],
    timeout: float,
    what: str,
    *,
    interval: float = 0.02,
    transient: tuple[str, ...] = (),
) -> Value:
    """Poll ``condition`` every ``interval`` s until it returns something truthy; that value.

    Exceptions whose class name is in ``transient`` (say a browser page re-rendered under us)
    count as "not yet"; any other propagates.  TimeoutError naming ``what`` (and the last
    value) after ``timeout`` seconds.
    """
    deadline = time.monotonic() + timeout
    last: Value | None = None
    while True:
        try:
            last = condition()
        except Exception as exc:
            if type(exc).__name__ not in transient:
                raise
            last = None
        if last:
            return last
        if time.monotonic() > deadline:
            raise TimeoutError(f"not reached after {timeout:.0f} s: {what} (last: {last!r})")
        time.sleep(interval)
