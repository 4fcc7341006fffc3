"""One typed settings object for the service (environment prefix ``SCANDIFF_``).

Every setting has a working local default: SQLite and the Huey queue file live in the data
directory, workers are local processes, nothing else needs to run.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """Service settings; ``SCANDIFF_DATA_DIR=/srv/scandiff`` etc. override the defaults."""

    model_config = SettingsConfigDict(env_prefix="SCANDIFF_", extra="ignore")

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
    job_lease_seconds: float = Field(default=60.0, gt=0)
    job_heartbeat_seconds: float = Field(default=10.0, gt=0)
    job_max_attempts: int = Field(default=3, ge=1)
    recovery_interval_seconds: float = Field(default=60.0, gt=0)
    job_memory_limit_bytes: int | None = Field(
        default=None, description="RLIMIT_AS for a worker process running a job; None = no cap."
    )
    max_concurrent_reads: int = Field(
        default=16, ge=1, description="GET requests in flight; more wait without a thread."
    )
    max_concurrent_writes: int = Field(
        default=8, ge=1, description="Other requests (uploads included) in flight."
    )
    view_link_ttl_seconds: int = Field(default=24 * 3600, gt=0)
    secret_key: str | None = Field(
        default=None, description="Signs view links and cookies; generated in data_dir if unset."
    )
    log_level: str = "INFO"

    @field_validator("data_dir")
    @classmethod
    def _absolute_data_dir(cls, value: Path) -> Path:
        return value.expanduser().resolve()

    @property
    def sqlalchemy_url(self) -> str:
        """The database URL in effect."""
        return self.database_url or f"sqlite:///{self.data_dir / 'scandiff.sqlite3'}"

    @property
    def queue_path(self) -> Path:
        """The Huey SQLite queue file (used when ``queue_url`` is unset)."""
        return self.data_dir / "queue.sqlite3"

    @property
    def scans_dir(self) -> Path:
        """Where uploaded scan files are stored."""
        return self.data_dir / "scans"

    @property
    def results_dir(self) -> Path:
        """Where per-point label files of jobs are stored."""
        return self.data_dir / "results"

    @property
    def tmp_dir(self) -> Path:
        """Where uploads are streamed before the atomic rename (same filesystem)."""
        return self.data_dir / "tmp"


@lru_cache
def get_settings() -> Settings:
    """The process-wide settings (read once from the environment)."""
    return Settings()
