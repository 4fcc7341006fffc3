"""The skip policy for missing dependencies (where the project and its data are: app.testing.paths).

Tests that need something outside the project (the real data in ../shared/data, a browser,
PostgreSQL, Redis) call :func:`require` instead of ``pytest.skip``: locally it skips with the
reason; in CI (``SCANDIFF_REQUIRE_SERVICES=1``) a missing dependency fails the test instead.
"""

from __future__ import annotations

import os

import pytest

from app.testing.paths import shared_data_dir as shared_data_dir  # the conftest files' import


def require(condition: bool, reason: str) -> None:
    """Skip (locally) or fail (in CI) when ``condition`` is false."""
    if condition:
        return
    if os.environ.get("SCANDIFF_REQUIRE_SERVICES") == "1":
        pytest.fail(f"required in CI but missing: {reason}")
    pytest.skip(reason)
