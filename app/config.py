"""One typed settings object for the service (environment prefix ``SCANDIFF_``).

Every setting has a working local default: SQLite and the Huey queue file live in the data
directory, workers are local processes, nothing else needs to run.
"""

from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import AliasChoices, Field, ValidationInfo, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from app.kit.data_layout import DataLayout
from app.kit.memory_budget import DEFAULT_MEMORY_BUDGET_BYTES

GIB = 1024**3
DISABLED_WORDS = frozenset({"none", "null", "off", "unlimited"})
"""Environment values that turn a cap off (as does 0 for the memory cap); empty = default."""


def _none_when_disabled(value: Any, default: Any) -> Any:
    """``"none"``, ``"off"``, ``"unlimited"`` (any case) as None, ``""`` as ``default``."""
    if isinstance(value, str):
        word = value.strip().lower()
        if word in DISABLED_WORDS:
            return None
        if word == "":
            return default
    return value


DEFAULT_TOKEN_CACHE_SECONDS = 5.0
"""Default of ``token_cache_seconds``: how long an API process trusts a token it authenticated
without reading its row again (:class:`app.services.auth.TokenCache`)."""

DEFAULT_VIEWER_POINT_BUDGET = 1_000_000
"""Default of ``viewer_point_budget``: the most points a job's 3D view sends to a browser."""

DEFAULT_VIEWER_STREAM_ABOVE_POINTS = 5_000_000
"""Default of ``viewer_stream_above_points``: larger clouds are not loaded whole by the view."""

DEFAULT_VIEWER_IDLE_SECONDS = 300.0
"""Default of ``viewer_idle_seconds``: how long a job's 3D view server outlives its last
browser connection."""


DEPRECATED_PRIVATE_ADDRESS_SETTINGS = (
    "SCANDIFF_WEBHOOK_ALLOW_PRIVATE_ADDRESSES",
    "SCANDIFF_SCHEDULE_ALLOW_PRIVATE_URLS",
)
"""Former environment names of ``allow_private_addresses`` (one for webhooks, one for schedule
URL sources), still accepted."""


class Settings(BaseSettings):
    """Service settings; ``SCANDIFF_DATA_DIR=/srv/scandiff`` etc. override the defaults."""

    model_config = SettingsConfigDict(env_prefix="SCANDIFF_", extra="ignore", populate_by_name=True)

    data_dir: Path = Field(default=Path("data"), description="Database, queue and scan files.")
    database_url: str | None = Field(
        default=None, description="SQLAlchemy URL; default sqlite file in data_dir."
    )
    queue_url: str | None = Field(
        default=None,
        description="Huey backend: a sqlite file in data_dir, or redis://host:port/db.",
    )
    host: str = "127.0.0.1"
    port: int = 8000
    workers: int = Field(default=2, ge=1, description="Job worker processes.")
    max_upload_bytes: int = Field(default=512 * 1024 * 1024, ge=1)
    max_points: int = Field(default=50_000_000, ge=10, description="Largest cloud accepted.")
    resumable_upload_expiry_seconds: int = Field(
        default=24 * 3600,
        gt=0,
        description="A resumable (tus) upload expires this long after its last accepted bytes.",
    )
    job_lease_seconds: float = Field(default=60.0, gt=0)
    job_heartbeat_seconds: float = Field(default=10.0, gt=0)
    job_max_attempts: int = Field(default=3, ge=1)
    recovery_interval_seconds: float = Field(default=60.0, gt=0)
    job_memory_limit_bytes: int | Literal["auto"] | None = Field(
        default="auto",
        description="RLIMIT_AS for a worker process running a job: 'auto' (derived from the "
        "machine's memory and the number of workers where the consumer starts), bytes, or "
        "0 / 'none' for no cap.",
    )
    tile_crop_points: int | None = Field(
        default=None,
        ge=1000,
        description="Compare every job in tiles of at most this many points (both clouds, "
        "margins included), fanned out on the queue, whatever the memory budget says; None = "
        "tiles only for a pair that does not fit a worker's memory budget.  For tests and "
        "for spreading mid-sized jobs over idle workers.",
    )
    min_free_disk_bytes: int = Field(
        default=1024**3,
        ge=0,
        description="Disk that must stay free under data_dir once a job's tile inputs and "
        "results are written: a tiled job whose files would leave less is refused at submit "
        "time when the pair alone cannot fit (422 insufficient_disk), else fails once planned "
        "with how much it needs and how much is free, before any crop is written.",
    )
    worker_memory_budget_bytes: int | None = Field(
        default=DEFAULT_MEMORY_BUDGET_BYTES,
        ge=1,
        description="Memory one comparison may use in a worker process (and `scandiff "
        "compare` by default: --memory-budget): a pair that does not fit is compared in "
        "tiles whose size follows from it (app/core/tiling, memory model in "
        "app/core/tiling/plan.py); a pair of which not even one tile fits fails with a "
        "message saying the budget to set.  None: always one process.",
    )
    job_threads: int | None = Field(
        default=None,
        ge=1,
        description="Threads one job may use (its localiser's KD-tree queries and the two "
        "sides of a comparison); None = the CPUs divided among the workers, at least 1.",
    )
    max_concurrent_reads: int = Field(
        default=16, ge=1, description="GET requests in flight; more wait without a thread."
    )
    max_concurrent_writes: int = Field(
        default=8, ge=1, description="Other requests (uploads included) in flight."
    )
    max_queued_jobs_per_organisation: int | None = Field(
        default=1000,
        ge=1,
        description="Unfinished (queued or running) jobs an organisation may have; more is a "
        "429. None / 'none' = unlimited.",
    )
    max_stored_bytes_per_organisation: int | None = Field(
        default=50 * GIB,
        ge=1,
        description="Bytes of scan files an organisation may store; more is a 507. "
        "None / 'none' = unlimited.",
    )
    view_link_ttl_seconds: int = Field(default=24 * 3600, gt=0)
    token_cache_seconds: float = Field(
        default=DEFAULT_TOKEN_CACHE_SECONDS,
        description="Seconds an API process trusts a token it authenticated without reading its "
        "row again (default 5, >= 0; 0 disables the cache). A revocation through `scandiff "
        "token revoke` ends cached uses at once; one made directly in the database is seen "
        "within this many seconds.",
    )
    viewer_point_budget: int = Field(
        default=DEFAULT_VIEWER_POINT_BUDGET,
        ge=1,
        description="The most points over all layers a job's 3D view sends to a browser "
        "(about 15 MB per million); larger clouds are subsampled, changed points first.",
    )
    viewer_stream_above_points: int = Field(
        default=DEFAULT_VIEWER_STREAM_ABOVE_POINTS,
        ge=0,
        description="A job's 3D view reads only the points it draws from the files (a block "
        "at a time, in bounded memory) when either cloud has more points than this; smaller "
        "jobs are loaded whole.",
    )
    viewer_idle_seconds: float = Field(
        default=DEFAULT_VIEWER_IDLE_SECONDS,
        gt=0,
        allow_inf_nan=False,
        description="Seconds a job's 3D view server keeps running after its last browser "
        "connection closed.",
    )
    shutdown_grace_seconds: float = Field(
        default=10.0,
        ge=0,
        allow_inf_nan=False,
        description="On SIGTERM, seconds a worker's running job may take to finish before it "
        "is interrupted and handed back to the queue without using an attempt.",
    )
    schedule_directory_roots: Annotated[list[Path], NoDecode] = Field(
        default_factory=list,
        description="Directories under which a schedule may read scans (source "
        "{'directory': ...}); none by default. In the environment: paths separated by "
        "os.pathsep (':') or commas.",
    )
    schedule_fetch_timeout_seconds: float = Field(
        default=60.0, gt=0, allow_inf_nan=False, description="Longest a URL source's fetch takes."
    )
    schedule_min_interval_seconds: int = Field(
        default=60, ge=1, description="Shortest interval_seconds a schedule may have."
    )
    schedule_tick_seconds: float = Field(
        default=15.0,
        gt=0,
        allow_inf_nan=False,
        description="How often the job consumer runs the schedules that are due.",
    )
    secret_key: str | None = Field(
        default=None, description="Signs view links and cookies; generated in data_dir if unset."
    )
    log_level: str = "INFO"
    log_format: Literal["json", "text"] = Field(
        default="json",
        description="Log lines on stderr: 'json' (one JSON object per line, with request_id "
        "and job_id where they apply) or 'text' (the same fields as key=value, for people).",
    )
    site_calibration_min_samples: int = Field(
        default=5,
        ge=1,
        description="Reviewed-null jobs (false alarm, or confirmed unchanged) a site needs "
        "before it learns its own thresholds from them.",
    )
    site_false_alarm_rate: float = Field(
        default=0.2,
        gt=0.0,
        lt=1.0,
        description="Target false-alarm rate of a site's learned thresholds (split-conformal "
        "upper bound of its reviewed-null jobs; at least ceil(1/rate) - 1 of them are needed).",
    )
    metrics_token: str | None = Field(
        default=None,
        description="When set, GET /metrics requires `Authorization: Bearer <metrics_token>`; "
        "unset (default), /metrics is public, as usual for Prometheus on a private network.",
    )

    # -- webhooks (issue 16: alerts) --
    public_url: str | None = Field(
        default=None,
        description="The service's address as people reach it (https://scandiff.example.com), "
        "for the view links in webhook payloads; default http://<host>:<port>.",
    )
    allow_private_addresses: bool = Field(
        default=False,
        validation_alias=AliasChoices(
            "SCANDIFF_ALLOW_PRIVATE_ADDRESSES",
            *DEPRECATED_PRIVATE_ADDRESS_SETTINGS,
        ),
        description="Let the service's own requests (webhooks, schedule URL sources) go to "
        "loopback, private, link-local and the other refused address classes listed in "
        "docs/webhooks.md (a receiver on this host or network). Off by default: an "
        "organisation cannot make the service call into its own network. The former "
        "SCANDIFF_WEBHOOK_ALLOW_PRIVATE_ADDRESSES and SCANDIFF_SCHEDULE_ALLOW_PRIVATE_URLS "
        "are deprecated aliases.",
    )
    webhook_max_attempts: int = Field(default=8, ge=1, description="Attempts per delivery.")
    event_retention_days: float = Field(
        default=30.0,
        gt=0,
        allow_inf_nan=False,
        description="Events (and their webhook deliveries) older than this are deleted by the "
        "recovery sweep once none of their deliveries is still pending or in flight.",
    )
    webhook_backoff_seconds: float = Field(
        default=10.0,
        gt=0,
        allow_inf_nan=False,
        description="Delay before the second attempt; doubles each attempt (with jitter).",
    )
    webhook_backoff_max_seconds: float = Field(
        default=3600.0, gt=0, allow_inf_nan=False, description="Longest delay between attempts."
    )
    webhook_timeout_seconds: float = Field(
        default=10.0, gt=0, allow_inf_nan=False, description="Time limit of one HTTP attempt."
    )
    webhook_lease_seconds: float = Field(
        default=60.0,
        gt=0,
        allow_inf_nan=False,
        description="How long a worker holds a delivery it claimed; a delivery of a dead "
        "worker is retried once its lease expires (at once when the worker ran on this host).",
    )
    webhook_poll_seconds: float = Field(
        default=1.0, gt=0, allow_inf_nan=False, description="How often deliveries are looked for."
    )

    smtp_host: str | None = Field(
        default=None,
        description="SMTP server for e-mail alerts (a webhook whose url is mailto:...); "
        "unset: e-mail alerts are refused.",
    )
    smtp_port: int = Field(default=587, ge=1, le=65535)
    smtp_security: Literal["starttls", "ssl", "none"] = Field(
        default="starttls",
        description="starttls (port 587), ssl (implicit TLS, port 465) or none (a local relay).",
    )
    smtp_username: str | None = None
    smtp_password: str | None = None
    smtp_from: str = Field(default="scandiff@localhost", description="The alerts' From address.")

    @field_validator("log_format", mode="before")
    @classmethod
    def _log_format_word(cls, value: Any) -> Any:
        return value.strip().lower() if isinstance(value, str) else value

    @field_validator("metrics_token", mode="before")
    @classmethod
    def _metrics_token_set(cls, value: Any) -> Any:
        return None if isinstance(value, str) and not value.strip() else value

    @field_validator(
        "max_queued_jobs_per_organisation", "max_stored_bytes_per_organisation", mode="before"
    )
    @classmethod
    def _unlimited_words(cls, value: Any, info: ValidationInfo) -> Any:
        return _none_when_disabled(value, cls.model_fields[str(info.field_name)].default)

    @field_validator("job_memory_limit_bytes", mode="before")
    @classmethod
    def _memory_limit(cls, value: Any) -> Any:
        value = _none_when_disabled(value, "auto")
        if isinstance(value, str) and value.strip().lower() == "auto":
            return "auto"
        if value is not None and not isinstance(value, bool) and int(value) == 0:
            return None
        return value

    @field_validator("job_memory_limit_bytes")
    @classmethod
    def _memory_limit_positive(cls, value: int | str | None) -> int | str | None:
        if isinstance(value, int) and value < 0:
            raise ValueError(
                "job_memory_limit_bytes must be 'auto', a positive number of bytes, "
                "or 0 / 'none' for no cap"
            )
        return value

    @field_validator("token_cache_seconds")
    @classmethod
    def _token_cache_seconds_valid(cls, value: float) -> float:
        if not 0 <= value < float("inf"):
            raise ValueError(
                "token_cache_seconds must be a finite number of seconds >= 0 (0 disables the "
                f"token cache), got {value}"
            )
        return value

    @field_validator("schedule_directory_roots", mode="before")
    @classmethod
    def _path_list(cls, value: Any) -> Any:
        if isinstance(value, str):
            parts = value.replace(",", os.pathsep).split(os.pathsep)
            return [part.strip() for part in parts if part.strip()]
        return value

    @field_validator("schedule_directory_roots")
    @classmethod
    def _resolved_roots(cls, value: list[Path]) -> list[Path]:
        return [root.expanduser().resolve() for root in value]

    @field_validator("data_dir")
    @classmethod
    def _absolute_data_dir(cls, value: Path) -> Path:
        return value.expanduser().resolve()

    @property
    def sqlalchemy_url(self) -> str:
        """The database URL in effect."""
        return self.database_url or f"sqlite:///{self.data_layout.database_file}"

    @property
    def public_base_url(self) -> str:
        """The service's address as people reach it (``public_url``, else host and port)."""
        return (self.public_url or f"http://{self.host}:{self.port}").rstrip("/")

    @property
    def data_layout(self) -> DataLayout:
        """Where each file lives under ``data_dir`` (:class:`app.kit.data_layout.DataLayout`)."""
        return DataLayout(self.data_dir)

    @property
    def queue_path(self) -> Path:
        """The Huey SQLite queue file (used when ``queue_url`` is unset)."""
        return self.data_layout.queue_file

    @property
    def scans_dir(self) -> Path:
        """Where uploaded scan files are stored."""
        return self.data_layout.scans_dir

    @property
    def results_dir(self) -> Path:
        """Where per-point label files of jobs are stored."""
        return self.data_layout.results_dir

    @property
    def tmp_dir(self) -> Path:
        """Where uploads are streamed before the atomic rename (same filesystem)."""
        return self.data_layout.tmp_dir

    @property
    def uploads_dir(self) -> Path:
        """Where resumable (tus) uploads keep their bytes between requests (kept on restart)."""
        return self.data_layout.uploads_dir


@lru_cache
def get_settings() -> Settings:
    """The process-wide settings (read once from the environment)."""
    return Settings()
