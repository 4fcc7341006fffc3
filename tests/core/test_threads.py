"""The numeric core's process-wide threading defaults."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

PROGRAM = "import os, app.core.localise; print(os.environ['OMP_WAIT_POLICY'])"


def wait_policy_after_import(environment: dict[str, str]) -> str:
    completed = subprocess.run(
        [sys.executable, "-c", PROGRAM],
        capture_output=True,
        text=True,
        check=True,
        env=environment,
    )
    return completed.stdout.strip()


@pytest.mark.parametrize(("given", "expected"), [(None, "PASSIVE"), ("ACTIVE", "ACTIVE")])
def test_importing_the_core_makes_openmp_waits_passive_unless_the_caller_chose(given, expected):
    environment = {name: value for name, value in os.environ.items() if name != "OMP_WAIT_POLICY"}
    if given is not None:
        environment["OMP_WAIT_POLICY"] = given
    assert wait_policy_after_import(environment) == expected
