"""The default memory budget of one comparison, without the settings layer's imports.

``app.config.Settings.worker_memory_budget_bytes`` defaults to it; ``scandiff compare`` reads
it directly when no variable of :data:`SETTING_VARIABLES` is set (building ``Settings`` imports
pydantic: 0.15 CPU seconds of a command's start-up).
"""

from __future__ import annotations

__all__ = ["DEFAULT_MEMORY_BUDGET_BYTES", "SETTING_VARIABLES"]

DEFAULT_MEMORY_BUDGET_BYTES = 2_684_354_560
"""2.5 GiB: issue 30's peak RSS target per worker process."""

SETTING_VARIABLES = frozenset(
    f"SCANDIFF_{name}"
    for name in (
        "ALLOW_PRIVATE_ADDRESSES",
        "DATABASE_URL",
        "DATA_DIR",
        "EVENT_RETENTION_DAYS",
        "HOST",
        "JOB_HEARTBEAT_SECONDS",
        "JOB_LEASE_SECONDS",
        "JOB_MAX_ATTEMPTS",
        "JOB_MEMORY_LIMIT_BYTES",
        "JOB_THREADS",
        "LOG_FORMAT",
        "LOG_LEVEL",
        "MAX_CONCURRENT_READS",
        "MAX_CONCURRENT_WRITES",
        "MAX_POINTS",
        "MAX_QUEUED_JOBS_PER_ORGANISATION",
        "MAX_STORED_BYTES_PER_ORGANISATION",
        "MAX_UPLOAD_BYTES",
        "METRICS_TOKEN",
        "MIN_FREE_DISK_BYTES",
        "PORT",
        "PUBLIC_URL",
        "QUEUE_URL",
        "RECOVERY_INTERVAL_SECONDS",
        "RESUMABLE_UPLOAD_EXPIRY_SECONDS",
        "SCHEDULE_ALLOW_PRIVATE_URLS",
        "SCHEDULE_DIRECTORY_ROOTS",
        "SCHEDULE_FETCH_TIMEOUT_SECONDS",
        "SCHEDULE_MIN_INTERVAL_SECONDS",
        "SCHEDULE_TICK_SECONDS",
        "SECRET_KEY",
        "SHUTDOWN_GRACE_SECONDS",
        "SITE_CALIBRATION_MIN_SAMPLES",
        "SITE_FALSE_ALARM_RATE",
        "SMTP_FROM",
        "SMTP_HOST",
        "SMTP_PASSWORD",
        "SMTP_PORT",
        "SMTP_SECURITY",
        "SMTP_USERNAME",
        "TILE_CROP_POINTS",
        "TOKEN_CACHE_SECONDS",
        "VIEWER_IDLE_SECONDS",
        "VIEWER_POINT_BUDGET",
        "VIEWER_STREAM_ABOVE_POINTS",
        "VIEW_LINK_TTL_SECONDS",
        "WEBHOOK_ALLOW_PRIVATE_ADDRESSES",
        "WEBHOOK_BACKOFF_MAX_SECONDS",
        "WEBHOOK_BACKOFF_SECONDS",
        "WEBHOOK_LEASE_SECONDS",
        "WEBHOOK_MAX_ATTEMPTS",
        "WEBHOOK_POLL_SECONDS",
        "WEBHOOK_TIMEOUT_SECONDS",
        "WORKERS",
        "WORKER_MEMORY_BUDGET_BYTES",
    )
)
"""The environment variables ``app.config.Settings`` reads (upper case; it matches them in any
case), its field names and aliases: any other ``SCANDIFF_*`` variable (``SCANDIFF_SHARED_DATA``,
the test suite's) changes no setting.  ``tests/cli/test_compare_budget_default.py`` checks the
list against ``Settings``."""
