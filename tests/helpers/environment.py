"""The skip policy for missing dependencies (where the project and its data are: app.testing.paths).

Tests that need something outside the project (the real data in ../shared/data, a browser,
PostgreSQL, Redis) call :func:`require` instead of ``pytest.skip``: locally it skips with the
reason; in CI (``SCANDIFF_REQUIRE_SERVICES=1``) a missing dependency fails the test instead.
"""

from __future__ import annotations

import os
import shutil
import sysconfig

import pytest

from app.testing.paths import shared_data_dir as shared_data_dir  # the conftest files' import


def require(condition: bool, reason: str) -> None:
    """Skip (locally) or fail (in CI) when ``condition`` is false."""
    if condition:
        return
    if os.environ.get("SCANDIFF_REQUIRE_SERVICES") == "1":
        pytest.fail(f"required in CI but missing: {reason}")
    pytest.skip(reason)


def c_compiler_found() -> bool:
    """Whether the C compiler setup.py would build the plane-fit kernel with is on the PATH.

    A machine without one installs the project all the same (the kernel is optional), so tests
    of the kernel skip there, in CI too."""
    compiler = (os.environ.get("CC") or sysconfig.get_config_var("CC") or "cc").split()[0]
    return shutil.which(compiler) is not None
