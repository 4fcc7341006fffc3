"""Where the project and its shared data are, and the skip policy for missing dependencies.

Tests that need something outside the project (the real data in ../shared/data, a browser,
PostgreSQL, Redis) call :func:`require` instead of ``pytest.skip``: locally it skips with the
reason; in CI (``SCANDIFF_REQUIRE_SERVICES=1``) a missing dependency fails the test instead.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

PROJECT_ROOT = Path(__file__).resolve().parent.parent.parent


def require(condition: bool, reason: str) -> None:
    """Skip (locally) or fail (in CI) when ``condition`` is false."""
    if condition:
        return
    if os.environ.get("SCANDIFF_REQUIRE_SERVICES") == "1":
        pytest.fail(f"required in CI but missing: {reason}")
    pytest.skip(reason)


def shared_data_dir() -> Path:
    """Where ../shared/data lives (override with SCANDIFF_SHARED_DATA)."""
    configured = os.environ.get("SCANDIFF_SHARED_DATA")
    if configured:
        return Path(configured)
    return PROJECT_ROOT.parent / "shared" / "data"
