"""The default memory budget of one comparison, without the settings layer's imports.

``app.config.Settings.worker_memory_budget_bytes`` defaults to it; ``scandiff compare`` reads
it directly when no ``SCANDIFF_*`` variable is set (building ``Settings`` imports pydantic:
0.15 CPU seconds of a command's start-up).
"""

from __future__ import annotations

__all__ = ["DEFAULT_MEMORY_BUDGET_BYTES"]

DEFAULT_MEMORY_BUDGET_BYTES = 2_684_354_560
"""2.5 GiB: issue 30's peak RSS target per worker process."""
