"""The test suite's layout: test modules import shared code from tests.helpers only.

Fixtures live in ``conftest.py`` files, where pytest finds them; plain functions and classes
shared between test modules live in ``tests/helpers``.  No module imports a test module or a
conftest, so moving or deleting a test never breaks another.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent


def is_allowed(module: str) -> bool:
    """Whether importing ``module`` from a test is allowed: anything but tests.<not helpers>."""
    parts = module.split(".")
    if "conftest" in parts:
        return False
    return parts[0] != "tests" or parts[1:2] in ([], ["helpers"])


def offending_imports(source: str) -> list[str]:
    """The imports in ``source`` (top-level and in functions) of test modules or conftests."""
    offenders = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            modules = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: always inside tests/
                modules = [f".{node.module or ''}"]
            else:
                base = node.module or ""
                modules = [f"{base}.{alias.name}" for alias in node.names]
        else:
            continue
        offenders.extend(
            f"line {node.lineno}: {module}"
            for module in modules
            if module.startswith(".") or not is_allowed(module)
        )
    return offenders


@pytest.mark.parametrize(
    ("source", "offends"),
    [
        ("from tests.helpers.http import unique_name", False),
        ("from tests.helpers import fake_pipeline", False),
        ("import numpy as np", False),
        ("from tests.api.conftest import upload", True),
        ("from tests.core import test_formats", True),
        ("import tests.jobs.test_serve", True),
        ("from tests.conftest import require", True),
        ("from tests import conftest", True),
        ("from .conftest import api", True),
        ("def f():\n    from tests.reliability.figures import record_figure", True),
    ],
)
def test_the_layout_check_tells_offending_imports(source: str, offends: bool) -> None:
    assert bool(offending_imports(source)) == offends


def test_no_module_imports_a_test_module_or_a_conftest() -> None:
    offenders = [
        f"{path.relative_to(TESTS.parent)} {offender}"
        for path in sorted(TESTS.rglob("*.py"))
        for offender in offending_imports(path.read_text())
    ]
    assert offenders == []
